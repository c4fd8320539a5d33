"""A numpy ray-caster that renders RGB and metric depth of a World from a camera pose.

It renders small (default 160 x 120) and upsamples to the output size, then adds sensor-like depth
noise (sigma growing with the square of range), dropouts and a maximum range, and image noise, so
that frames compress like a real camera's. Pure: no I/O; the random generator is seeded.

Camera frame: x right, y down, z forward (optical axis). The camera looks along the body's x axis
(forward), so camera (x, y, z) = body (y, z, x).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dynqos.sim.vehicle.world import World

Array = NDArray[np.float64]
F32 = NDArray[np.float32]

# camera axes expressed in the body frame (columns): x_cam = body y, y_cam = body z, z_cam = body x
CAM_TO_BODY = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
LIGHT = np.array([0.3, -0.4, -0.85]) / np.linalg.norm([0.3, -0.4, -0.85])  # towards the light, NED


@dataclass(frozen=True, slots=True, kw_only=True)
class Intrinsics:
    width: int = 640
    height: int = 480
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5

    def scaled(self, width: int, height: int) -> Intrinsics:
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            width=width,
            height=height,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
        )

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (self.fx, self.fy, self.cx, self.cy)

    def ray_directions(self) -> Array:
        """Per pixel, the camera-frame direction with unit z: depth along the axis is the ray parameter."""
        u, v = np.meshgrid(np.arange(self.width), np.arange(self.height))
        dirs: Array = np.stack([(u - self.cx) / self.fx, (v - self.cy) / self.fy, np.ones_like(u, float)], -1)
        return dirs


@dataclass(frozen=True, slots=True, kw_only=True)
class DepthNoise:
    sigma_per_m2: float = 0.0012  # Kinect-like: sigma = k z^2
    dropout: float = 0.02
    max_range_m: float = 10.0
    rgb_sigma: float = 3.0


class Renderer:
    def __init__(
        self,
        world: World,
        intrinsics: Intrinsics | None = None,
        *,
        render_size: tuple[int, int] = (160, 120),
        noise: DepthNoise | None = None,
        seed: int = 0,
    ) -> None:
        self.world = world
        self.intrinsics = intrinsics or Intrinsics()
        self.small = self.intrinsics.scaled(*render_size)
        self.noise = noise or DepthNoise()
        self._rng = np.random.default_rng(seed)
        self._dirs = self.small.ray_directions().reshape(-1, 3).astype(np.float32)
        # Sensor noise from a small bank of precomputed frames: drawing fresh noise for every 640 x 480
        # frame would cost more than the ray casting itself.
        shape = (self.intrinsics.height, self.intrinsics.width)
        texture = self._rng.integers(-12, 13, size=(*shape, 1)).astype(np.float32)
        self._rgb_noise = [
            texture + self._rng.normal(0.0, self.noise.rgb_sigma, (*shape, 3)).astype(np.float32)
            for _ in range(4)
        ]
        self._depth_noise = [self._rng.normal(0.0, 1.0, shape).astype(np.float32) for _ in range(4)]
        self._dropouts = [self._rng.random(shape) < self.noise.dropout for _ in range(4)]

    def render(
        self, pos_m: Array, rot_body_to_ned: Array, *, noisy: bool = True
    ) -> tuple[NDArray[np.uint8], Array]:
        """RGB (H x W x 3, uint8, RGB order) and depth (H x W, metres, 0 = no reading)."""
        rot = rot_body_to_ned @ CAM_TO_BODY
        dirs = self._dirs @ rot.T.astype(np.float32)  # world-frame directions, z_cam component 1
        depth, normal, color, checker = self._cast(np.asarray(pos_m, dtype=np.float32), dirs)
        h, w = self.small.height, self.small.width
        shade = 0.35 + 0.65 * np.clip(-(normal @ LIGHT.astype(np.float32)), 0.0, 1.0)
        rgb_small = (color * (shade * checker)[:, None]).reshape(h, w, 3)
        size = (self.intrinsics.width, self.intrinsics.height)
        rgb: NDArray[np.float32] = cv2.resize(rgb_small, size, interpolation=cv2.INTER_LINEAR)
        depth_full = np.asarray(
            cv2.resize(depth.reshape(h, w), size, interpolation=cv2.INTER_NEAREST), dtype=np.float32
        )
        if noisy:
            k = int(self._rng.integers(len(self._rgb_noise)))
            rgb += self._rgb_noise[k]
            depth_full += self._depth_noise[k] * self.noise.sigma_per_m2 * depth_full * depth_full
            depth_full[self._dropouts[k]] = 0.0
        depth_full[(depth_full > self.noise.max_range_m) | ~np.isfinite(depth_full)] = 0.0
        np.maximum(depth_full, 0.0, out=depth_full)
        return np.clip(rgb, 0, 255).astype(np.uint8), depth_full.astype(np.float64)

    def _cast(self, o: F32, d: F32) -> tuple[F32, F32, F32, F32]:
        """Nearest hit per ray: depth, surface normal, base colour and texture factor."""
        best, axis, hit_id, shapes = self._intersect(o, d)
        normal, color, checker = self._shade(o, d, best, axis, hit_id, shapes)
        return best, normal, color, checker

    def _intersect(self, o: F32, d: F32) -> tuple[F32, Any, Any, list[tuple[str, object]]]:
        """Per ray: the distance to the nearest surface, the arena wall's axis it would hit, and which of
        `shapes` it hit (-1: the arena)."""
        n = len(d)
        arena = self.world.arena
        lx, ly, lz = arena.size_m
        lo = np.array([-lx / 2, -ly / 2, -lz], np.float32)
        hi = np.array([lx / 2, ly / 2, 0.0], np.float32)
        # One reciprocal for every slab test; an exactly axis-parallel ray gets a tiny component instead
        # of a zero so that no inf * 0 = NaN can appear.
        inv_d = 1.0 / np.where(np.abs(d) < 1e-9, np.float32(1e-9), d)
        t_planes = np.where(d > 0, hi - o, lo - o) * inv_d
        # argmin over the three slabs, by columns (numpy's reductions over a last axis of three are slow):
        # the first of equal minima, as argmin takes
        t0, t1, t2 = t_planes[:, 0], t_planes[:, 1], t_planes[:, 2]
        t12 = np.minimum(t1, t2)
        first = t0 <= t12
        axis = np.where(first, 0, np.where(t1 <= t2, 1, 2))
        best = np.where(first, t0, t12)
        hit_id = np.full(n, -1, np.int32)  # -1: the arena
        shapes: list[tuple[str, object]] = []
        inv = [np.ascontiguousarray(inv_d[:, k]) for k in range(3)]  # per-axis rows: contiguous, fast
        dx, dy, dz = (np.ascontiguousarray(d[:, k]) for k in range(3))
        a = dx * dx + dy * dy  # the same for every cylinder

        for box in self.world.boxes:
            t_enter = np.full(n, -np.inf, np.float32)
            t_exit = np.full(n, np.inf, np.float32)
            for k in range(3):
                t1 = (box.min_m[k] - o[k]) * inv[k]
                t2 = (box.max_m[k] - o[k]) * inv[k]
                np.maximum(t_enter, np.minimum(t1, t2), out=t_enter)
                np.minimum(t_exit, np.maximum(t1, t2), out=t_exit)
            closer = (t_enter <= t_exit) & (t_enter > 1e-6) & (t_enter < best)
            best[closer] = t_enter[closer]
            hit_id[closer] = len(shapes)
            shapes.append(("box", box))

        for cyl in self.world.cylinders:
            ox, oy = o[0] - cyl.center_m[0], o[1] - cyl.center_m[1]
            b = 2 * (ox * dx + oy * dy)
            disc = b * b - 4 * a * (ox * ox + oy * oy - cyl.radius_m**2)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
            z = o[2] + dz * t
            closer = (disc >= 0) & (z >= cyl.z_top_m) & (z <= cyl.z_bottom_m) & (t > 1e-6) & (t < best)
            best[closer] = t[closer]
            hit_id[closer] = len(shapes)
            shapes.append(("cylinder", cyl))

        for hoop in self.world.hoops:
            nvec = (np.array(hoop.normal) / np.linalg.norm(hoop.normal)).astype(np.float32)
            center = np.array(hoop.center_m, np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((center - o) @ nvec) / (d @ nvec)
            rel = [o[k] - center[k] + d[:, k] * t for k in range(3)]
            r = np.sqrt(rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2])
            closer = np.isfinite(t) & (np.abs(r - hoop.radius_m) <= hoop.tube_m) & (t > 1e-6) & (t < best)
            best[closer] = t[closer]
            hit_id[closer] = len(shapes)
            shapes.append(("hoop", hoop))
        return best, axis, hit_id, shapes

    def _shade(
        self, o: F32, d: F32, best: F32, axis: Any, hit_id: Any, shapes: list[tuple[str, object]]
    ) -> tuple[F32, F32, F32]:
        """Shade only what was hit: normals, colours and texture per surface. Computed for every ray and
        chosen by mask, not gathered by mask first: numpy's boolean row gathers cost more than the sums."""
        n = len(d)
        rows = np.arange(n)
        arena = self.world.arena
        points = o + d * best[:, None]  # where each ray hits
        normal = np.zeros((n, 3), np.float32)
        walls = hit_id < 0
        wall_rows = rows[walls]
        wall_axis = axis[walls]
        normal[wall_rows, wall_axis] = -np.sign(d[wall_rows, wall_axis])
        # the arena's colour by ray (wall, floor or ceiling); a shape's rays are painted over below
        flat = axis == 2
        dz = d[:, 2]
        base = np.where(flat & (dz > 0), 1, np.where(flat & (dz < 0), 2, 0))
        palette = np.array([arena.wall_color, arena.floor_color, arena.ceiling_color], np.float32)
        color: F32 = palette[base]
        cells = np.floor(points * 2)
        checker: F32 = np.where(walls, 0.85 + 0.15 * ((cells[:, 0] + cells[:, 1] + cells[:, 2]) % 2), 1.0)
        for index, (kind, shape) in enumerate(shapes):
            mask = hit_id == index
            if not mask.any():
                continue
            color[mask] = shape.color  # type: ignore[attr-defined]
            if kind == "box":
                p = points[mask]
                bmin, bmax = np.array(shape.min_m), np.array(shape.max_m)  # type: ignore[attr-defined]
                dist = np.minimum(np.abs(p - bmin), np.abs(p - bmax))
                face = np.argmin(dist, axis=1)
                normal[rows[mask], face] = -np.sign(d[rows[mask], face])
            elif kind == "cylinder":
                p = points[mask]
                cx, cy = shape.center_m  # type: ignore[attr-defined]
                normal[mask, 0] = (p[:, 0] - cx) / shape.radius_m  # type: ignore[attr-defined]
                normal[mask, 1] = (p[:, 1] - cy) / shape.radius_m  # type: ignore[attr-defined]
            else:  # hoops are painted markers: lit evenly, whatever their orientation
                normal[mask] = -LIGHT.astype(np.float32)
        return normal, color, checker

    def project(
        self, point_ned: Array, pos_m: Array, rot_body_to_ned: Array
    ) -> tuple[float, float, float] | None:
        """Pixel (u, v) and depth of a world point in the output image, or None if behind the camera."""
        rot = rot_body_to_ned @ CAM_TO_BODY
        p_cam = rot.T @ (np.asarray(point_ned, float) - np.asarray(pos_m, float))
        if p_cam[2] <= 1e-6:
            return None
        k = self.intrinsics
        return (k.fx * p_cam[0] / p_cam[2] + k.cx, k.fy * p_cam[1] / p_cam[2] + k.cy, float(p_cam[2]))
