"""Missions as reference trajectories of mission time: hover, circle, figure-eight, waypoints. Pure.

Each mission maps t (seconds since the mission started) to a position, velocity and yaw in local NED.
Before t = lead_in_s the drone is led to the start point; the mission proper starts at lead_in_s.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dynqos.common.errors import ConfigError

Sample = tuple[tuple[float, float, float], tuple[float, float, float], float]


@dataclass(frozen=True, slots=True, kw_only=True)
class Mission:
    kind: str = "circle"  # hover | circle | figure8 | waypoints
    center_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 1.5
    radius_m: float = 2.0
    period_s: float = 10.0
    yaw: str = "tangent"  # tangent | fixed | center
    fixed_yaw_rad: float = 0.0
    lead_in_s: float = 5.0
    waypoints: tuple[tuple[float, float, float], ...] = ()  # NED, for kind = waypoints
    speed_mps: float = 1.0

    def sample(self, t: float) -> Sample:
        t_m = max(0.0, t - self.lead_in_s)
        if self.kind == "hover":
            return (self.center_m[0], self.center_m[1], -self.altitude_m), (0.0, 0.0, 0.0), self.fixed_yaw_rad
        if self.kind == "waypoints":
            return self._waypoint(t_m)
        w = 2 * math.pi / self.period_s
        cx, cy, r = self.center_m[0], self.center_m[1], self.radius_m
        if self.kind == "circle":
            pos = (cx + r * math.cos(w * t_m), cy + r * math.sin(w * t_m), -self.altitude_m)
            vel = (
                (-r * w * math.sin(w * t_m), r * w * math.cos(w * t_m), 0.0)
                if t >= self.lead_in_s
                else (0.0,) * 3
            )
        else:  # figure8: a lemniscate of Gerono, x = r sin(wt), y = r sin(wt) cos(wt)
            pos = (
                cx + r * math.sin(w * t_m),
                cy + r * math.sin(w * t_m) * math.cos(w * t_m),
                -self.altitude_m,
            )
            vel = (
                (r * w * math.cos(w * t_m), r * w * math.cos(2 * w * t_m), 0.0)
                if t >= self.lead_in_s
                else (0.0,) * 3
            )
        return pos, vel, self._yaw(pos, self._direction(t_m, w))

    def _direction(self, t_m: float, w: float) -> tuple[float, float]:
        if self.kind == "circle":
            return -math.sin(w * t_m), math.cos(w * t_m)
        return math.cos(w * t_m), math.cos(2 * w * t_m)

    def _yaw(self, pos: tuple[float, float, float], direction: tuple[float, float]) -> float:
        if self.yaw == "fixed":
            return self.fixed_yaw_rad
        if self.yaw == "center":
            return math.atan2(self.center_m[1] - pos[1], self.center_m[0] - pos[0])
        return math.atan2(direction[1], direction[0])

    def _waypoint(self, t_m: float) -> Sample:
        points = [np.array(p, float) for p in self.waypoints]
        travelled = t_m * self.speed_mps
        for a, b in itertools.pairwise(points):
            leg = float(np.linalg.norm(b - a))
            if travelled <= leg and leg > 0:
                direction = (b - a) / leg
                pos = a + direction * travelled
                vel = direction * self.speed_mps
                return (
                    (float(pos[0]), float(pos[1]), float(pos[2])),
                    (float(vel[0]), float(vel[1]), float(vel[2])),
                    math.atan2(direction[1], direction[0]),
                )
            travelled -= leg
        last = points[-1]
        return (float(last[0]), float(last[1]), float(last[2])), (0.0, 0.0, 0.0), self._arrival_yaw(points)

    def _arrival_yaw(self, points: list[np.ndarray]) -> float:
        """Where the drone looks once it holds the last waypoint: along its last leg (not a turn to
        `fixed_yaw_rad` on arrival), or `fixed_yaw_rad` if it never moved."""
        for a, b in itertools.pairwise(reversed(points)):
            if float(np.linalg.norm(a[:2] - b[:2])) > 1e-6:
                return math.atan2(a[1] - b[1], a[0] - b[0])
        return self.fixed_yaw_rad

    def samples(
        self, t0: float, dt: float, count: int
    ) -> tuple[
        tuple[tuple[float, float, float], ...], tuple[tuple[float, float, float], ...], tuple[float, ...]
    ]:
        """Positions, velocities and yaws at t0, t0 + dt, ... (count samples)."""
        sampled = [self.sample(t0 + k * dt) for k in range(count)]
        return tuple(s[0] for s in sampled), tuple(s[1] for s in sampled), tuple(s[2] for s in sampled)


def outside_arena(
    points: tuple[tuple[float, float, float], ...],
    arena_min_m: tuple[float, float, float],
    arena_max_m: tuple[float, float, float],
) -> str | None:
    """Why a mission from outside may not be flown (its first waypoint outside the arena), or None."""
    for index, point in enumerate(points):
        for axis, value, low, high in zip("xyz", point, arena_min_m, arena_max_m, strict=True):
            if not low <= value <= high:
                return (
                    f"waypoint {index} ({point[0]:.2f}, {point[1]:.2f}, {point[2]:.2f}) NED is outside the "
                    f"arena: {axis} must be in {low:g}..{high:g} m"
                )
    return None


def load_waypoints(path: str | Path) -> tuple[tuple[float, float, float], ...]:
    """A waypoint file: one `x y z` (NED metres) per line; # comments and blank lines allowed."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError("planner.waypoints_file", f"cannot read {path} ({exc.strerror})") from None
    points = []
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.replace(",", " ").split()
        try:
            x, y, z = (float(v) for v in parts)
        except ValueError:
            raise ConfigError(
                "planner.waypoints_file", f"{path}:{number}: expected 'x y z', got {text!r}"
            ) from None
        if not all(math.isfinite(v) for v in (x, y, z)):
            raise ConfigError("planner.waypoints_file", f"{path}:{number}: non-finite coordinate")
        points.append((x, y, z))
    if len(points) < 2:
        raise ConfigError("planner.waypoints_file", f"{path}: need at least two waypoints")
    return tuple(points)
