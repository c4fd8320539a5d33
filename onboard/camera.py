"""Camera sources and encoders for the onboard daemon.

Sources: `sim` renders RGB-D from the world and the drone's current pose with sim/'s renderer;
`files` replays a folder of RGB-D frames (color_N.png + depth_N.pgm, 16-bit millimetres, like
shared/data/rgbd); `device` grabs RGB from an OpenCV capture device (no depth). Encoders: JPEG for RGB,
zstd16 (byte shuffle + zstd, lossless) for depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from dynqos.common.depthcodec import encode_zstd16
from dynqos.common.errors import ConfigError
from dynqos.sim.dynamics import quat_to_rot
from dynqos.sim.render import Intrinsics, Renderer
from dynqos.sim.world import World

Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]


@dataclass(frozen=True, slots=True)
class RawFrame:
    rgb: NDArray[np.uint8]  # H x W x 3, RGB
    depth_m: NDArray[np.float32] | None  # H x W metres, 0 = no reading
    intrinsics: tuple[float, float, float, float]


class CameraSource(Protocol):
    def grab(self, pose: Pose | None) -> RawFrame | None: ...


class SimCamera:
    def __init__(self, world: World, width: int, height: int, seed: int = 0) -> None:
        intrinsics = Intrinsics(width=width, height=height, fx=525.0 * width / 640, fy=525.0 * height / 480,
                                cx=(width - 1) / 2, cy=(height - 1) / 2)  # fmt: skip
        # Rays are cast at 160 x 120 at most and the image resized; a smaller image (a fleet's scaled
        # camera) casts no more rays than it has pixels.
        render_size = (min(160, width), min(120, height))
        self.renderer = Renderer(world, intrinsics, render_size=render_size, seed=seed)

    def grab(self, pose: Pose | None) -> RawFrame | None:
        if pose is None:
            return None
        pos, quat = pose
        rgb, depth = self.renderer.render(np.array(pos), quat_to_rot(np.array(quat)))
        return RawFrame(rgb, depth.astype(np.float32), self.renderer.intrinsics.as_tuple())


class FilesCamera:
    """Replays color_N.png / depth_N.pgm pairs in order, looping."""

    def __init__(
        self, folder: str | Path, intrinsics: tuple[float, float, float, float], depth_unit_m: float = 0.001
    ):
        root = Path(folder)
        colors = sorted(root.glob("color_*.png"), key=_frame_number)
        if not colors:
            raise ConfigError("onboard.files_dir", f"no color_N.png frames in {folder}")
        self.frames: list[RawFrame] = []
        for color in colors:
            rgb = cv2.imread(str(color), cv2.IMREAD_COLOR)
            if rgb is None:
                raise ConfigError("onboard.files_dir", f"cannot read {color}")
            depth_path = root / color.name.replace("color_", "depth_").replace(".png", ".pgm")
            depth = None
            raw = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED) if depth_path.exists() else None
            if raw is not None and raw.dtype == np.uint16:
                depth = raw.astype(np.float32) * np.float32(depth_unit_m)
            self.frames.append(
                RawFrame(np.asarray(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB), np.uint8), depth, intrinsics)
            )
        self._next = 0

    def grab(self, pose: Pose | None) -> RawFrame | None:
        frame = self.frames[self._next % len(self.frames)]
        self._next += 1
        return frame


def _frame_number(path: Path) -> int:
    suffix = path.stem.split("_", 1)[1]
    return int(suffix) if suffix.isdigit() else 0


class DeviceCamera:
    def __init__(self, index: int, width: int, height: int, intrinsics: tuple[float, float, float, float]):
        self.capture = cv2.VideoCapture(index)
        if not self.capture.isOpened():
            raise ConfigError("onboard.device_index", f"cannot open camera device {index}")
        self.capture.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        self.capture.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        self.intrinsics = intrinsics

    def grab(self, pose: Pose | None) -> RawFrame | None:
        ok, bgr = self.capture.read()
        if not ok:
            return None
        return RawFrame(np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), np.uint8), None, self.intrinsics)


def encode_rgb(rgb: NDArray[np.uint8], quality: int) -> bytes:
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return data.tobytes()


def encode_depth(depth_m: NDArray[np.float32], unit_m: float = 0.001) -> bytes:
    counts = np.clip(np.round(depth_m / unit_m), 0, 65535).astype(np.uint16)
    return encode_zstd16(counts)


class RateController:
    """Frames per second = nominal x the supervisor's rate factor; `due(now)` says when to grab."""

    def __init__(self, nominal_fps: float) -> None:
        self.nominal_fps = nominal_fps
        self.factor = 1.0
        self._next_ns = 0

    def due(self, now_ns: int) -> bool:
        if self.nominal_fps <= 0 or self.factor <= 0:
            return False
        if now_ns < self._next_ns:
            return False
        period_ns = round(1e9 / (self.nominal_fps * self.factor))
        self._next_ns = (
            max(self._next_ns + period_ns, now_ns - period_ns) if self._next_ns else now_ns + period_ns
        )
        return True

    def wait_s(self, now_ns: int) -> float:
        return max(0.0, (self._next_ns - now_ns) / 1e9) if self._next_ns else 0.0
