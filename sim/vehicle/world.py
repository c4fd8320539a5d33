"""The world the simulated drone flies in: an arena (floor, ceiling, walls), boxes, vertical cylinders
and circular hoops, in local NED metres (z down, the floor at z = 0). Loaded from TOML or JSON.

The default arena is 7 x 7 x 3 m around the origin. Along a 2 m circle at 1.5 m altitude around the
origin (the demo's mission), looking along the path, the spaciousness is 3.1-3.7 m (medium risk); facing
the cluster of pillars near +y it drops to about 2 m (high risk). Hoops stand on the circle.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dynqos.common.config import build
from dynqos.common.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

Color = tuple[int, int, int]


def _color_ok(color: Color, key: str) -> None:
    if not all(0 <= c <= 255 for c in color):
        raise ConfigError(key, "colour components must be 0..255")


@dataclass(frozen=True, slots=True, kw_only=True)
class Arena:
    size_m: tuple[float, float, float] = (7.0, 7.0, 3.0)
    wall_color: Color = (180, 170, 150)
    floor_color: Color = (90, 100, 110)
    ceiling_color: Color = (220, 220, 215)

    def __post_init__(self) -> None:
        if not all(0.5 <= s <= 1000 for s in self.size_m):
            raise ConfigError("size_m", "each size must be 0.5..1000 m")
        for name in ("wall_color", "floor_color", "ceiling_color"):
            _color_ok(getattr(self, name), name)


@dataclass(frozen=True, slots=True, kw_only=True)
class Box:
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]
    color: Color = (160, 60, 50)

    def __post_init__(self) -> None:
        if not all(lo < hi for lo, hi in zip(self.min_m, self.max_m, strict=True)):
            raise ConfigError("max_m", "must exceed min_m on every axis")
        _color_ok(self.color, "color")


@dataclass(frozen=True, slots=True, kw_only=True)
class Cylinder:
    """A vertical cylinder between z_top_m and z_bottom_m (NED: top is the more negative z)."""

    center_m: tuple[float, float]
    radius_m: float
    z_top_m: float = -4.0
    z_bottom_m: float = 0.0
    color: Color = (60, 120, 170)

    def __post_init__(self) -> None:
        if not 0.01 <= self.radius_m <= 100:
            raise ConfigError("radius_m", "must be 0.01..100 m")
        if not self.z_top_m < self.z_bottom_m:
            raise ConfigError("z_top_m", "must be above (more negative than) z_bottom_m")
        _color_ok(self.color, "color")


@dataclass(frozen=True, slots=True, kw_only=True)
class Hoop:
    """A circular hoop: a ring of radius radius_m and half-width tube_m in the plane normal to `normal`."""

    center_m: tuple[float, float, float]
    radius_m: float = 0.6
    tube_m: float = 0.08
    normal: tuple[float, float, float] = (1.0, 0.0, 0.0)
    color: Color = (240, 140, 20)

    def __post_init__(self) -> None:
        if not 0.05 <= self.radius_m <= 50 or not 0.005 <= self.tube_m < self.radius_m:
            raise ConfigError("radius_m", "need 0.05 <= radius_m <= 50 and 0.005 <= tube_m < radius_m")
        if math.hypot(*self.normal) < 1e-6:
            raise ConfigError("normal", "must not be zero")
        _color_ok(self.color, "color")


@dataclass(frozen=True, slots=True, kw_only=True)
class World:
    arena: Arena = field(default_factory=Arena)
    boxes: tuple[Box, ...] = ()
    cylinders: tuple[Cylinder, ...] = ()
    hoops: tuple[Hoop, ...] = ()


def default_world() -> World:
    return World(
        arena=Arena(),
        cylinders=(  # high-risk zone: pillars around the circle near +y
            Cylinder(center_m=(-0.8, 3.2), radius_m=0.3, z_top_m=-3.0),
            Cylinder(center_m=(0.8, 3.3), radius_m=0.3, z_top_m=-3.0),
            Cylinder(center_m=(0.0, 3.1), radius_m=0.3, z_top_m=-3.0),
        ),
        boxes=(  # medium-risk zone: crates near -x
            Box(min_m=(-3.4, -1.2, -1.2), max_m=(-2.8, 1.2, 0.0)),
            Box(min_m=(-3.4, -3.0, -2.0), max_m=(-2.9, -2.0, 0.0), color=(120, 90, 60)),
        ),
        hoops=(
            Hoop(center_m=(2.0, 0.0, -1.5), radius_m=0.6, normal=(0.0, 1.0, 0.0)),
            Hoop(center_m=(0.0, -2.0, -1.5), radius_m=0.5, normal=(1.0, 0.0, 0.0), color=(30, 200, 60)),
        ),
    )


def load_world(path: str | Path) -> World:
    """A world from a TOML or JSON file; errors name the file and the key."""
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError("", f"cannot read world file ({exc.strerror})", source=source) from None
    try:
        table: Any = json.loads(text) if source.endswith(".json") else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError("", f"not a valid world file ({exc})", source=source) from None
    if not isinstance(table, dict):
        raise ConfigError("", "a world file is a table", source=source)
    try:
        return build(World, table)
    except ConfigError as exc:
        raise exc.with_source(source) from None


def collision(world: World, pos_m: tuple[float, float, float], radius_m: float = 0.15) -> str | None:
    """What a sphere of `radius_m` at `pos_m` touches, as a name ("cylinder 2"), or None.

    The vehicle uses it to report crashes: a run that looked fine on the error plot but flew through a
    pillar should not pass unnoticed. The floor is not an obstacle (the vehicle lands on it).
    """
    x, y, z = pos_m
    size_x, size_y, height = world.arena.size_m
    half_x, half_y = size_x / 2, size_y / 2
    if abs(x) + radius_m > half_x or abs(y) + radius_m > half_y:
        return "arena wall"
    if -z + radius_m > height:
        return "arena ceiling"
    for i, box in enumerate(world.boxes):
        nearest = [min(max(p, lo), hi) for p, lo, hi in zip(pos_m, box.min_m, box.max_m, strict=True)]
        if math.dist(nearest, pos_m) < radius_m:
            return f"box {i}"
    for i, cyl in enumerate(world.cylinders):
        if cyl.z_top_m - radius_m < z < cyl.z_bottom_m + radius_m and (
            math.hypot(x - cyl.center_m[0], y - cyl.center_m[1]) < cyl.radius_m + radius_m
        ):
            return f"cylinder {i}"
    for i, hoop in enumerate(world.hoops):
        if _hoop_distance(hoop, pos_m) < hoop.tube_m + radius_m:
            return f"hoop {i}"
    return None


def _hoop_distance(hoop: Hoop, pos_m: tuple[float, float, float]) -> float:
    """Distance from a point to the hoop's centre circle (the torus's core)."""
    norm = math.hypot(*hoop.normal)
    n = [c / norm for c in hoop.normal]
    d = [p - c for p, c in zip(pos_m, hoop.center_m, strict=True)]
    along = sum(a * b for a, b in zip(d, n, strict=True))
    in_plane = math.sqrt(max(0.0, sum(c * c for c in d) - along * along))
    return math.hypot(in_plane - hoop.radius_m, along)
