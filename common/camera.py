"""What a camera source gives the onboard daemon: the frame type and the source protocol.

The drone's own sources (a folder of frames, a capture device) live in onboard/camera.py; the
simulator's rendered camera in sim/vehicle/camera.py. Both implement `CameraSource`, so the daemon is
handed whichever its starter chose and never imports the simulator."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

# The drone's pose as the flight controller reports it: position (m, NED) and attitude (w, x, y, z).
Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]


@dataclass(frozen=True, slots=True)
class RawFrame:
    rgb: NDArray[np.uint8]  # H x W x 3, RGB
    depth_m: NDArray[np.float32] | None  # H x W metres, 0 = no reading
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy in pixels
    captured_ns: int | None = None  # on the daemon's clock, from the device's stamp (None: when grabbed)


class CameraSource(Protocol):
    def grab(self, pose: Pose | None) -> RawFrame | None:
        """The next frame (None: nothing this time); `pose` for a source that renders from it."""
        ...
