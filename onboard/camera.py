"""The drone's own camera sources and the encoders for the onboard daemon.

Sources (common/camera.py's `CameraSource`): `files` replays a folder of RGB-D frames (color_N.png +
depth_N.pgm, 16-bit millimetres); `device` grabs RGB from an OpenCV capture device (no depth). The
simulator's rendered camera (`sim`) is sim/vehicle/camera.py, handed to the daemon by whoever starts it.
Encoders: JPEG for RGB, zstd16 (byte shuffle + zstd, lossless) for depth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from dynqos.common.camera import Pose, RawFrame
from dynqos.common.depthcodec import encode_zstd16
from dynqos.common.errors import ConfigError


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


DEPTH_ENCODING = "zstd16"  # what encode_depth makes (common/depthcodec.py)


def encode_depth(depth_m: NDArray[np.floating], unit_m: float = 0.001) -> bytes:
    """Metres to counts of `unit_m` (rounded half to even, clipped to 16 bits) in one buffer, then
    DEPTH_ENCODING."""
    counts = np.divide(depth_m, unit_m)
    np.rint(counts, out=counts)
    np.clip(counts, 0, 65535, out=counts)
    return encode_zstd16(counts.astype(np.uint16))


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
