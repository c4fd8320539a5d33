"""Spaciousness S_k: the mean Euclidean distance from the camera to the points of the depth cloud.

The paper's risk input (eq. for s_k). A depth pixel at (u, v) with axis depth z is the point
z * ((u - cx) / fx, (v - cy) / fy, 1), whose distance from the camera is z times a per-pixel ray-length
factor; the factors are computed once per image size, so each frame costs one masked mean.
Pixels with no reading (0) are left out. Pure numpy, no I/O.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class Spaciousness:
    def __init__(
        self, width: int, height: int, intrinsics: tuple[float, float, float, float], stride: int = 2
    ):
        fx, fy, cx, cy = intrinsics
        if fx <= 0 or fy <= 0 or width < 1 or height < 1 or stride < 1:
            raise ValueError("need positive focal lengths, image size and stride")
        self.shape = (height, width)
        self.stride = stride
        u, v = np.meshgrid(np.arange(0, width, stride), np.arange(0, height, stride))
        self._factor = np.sqrt(1.0 + ((u - cx) / fx) ** 2 + ((v - cy) / fy) ** 2).astype(np.float32)

    def __call__(self, depth_m: NDArray[np.floating]) -> float | None:
        """S_k in metres, or None when the frame has no valid reading (or the wrong size)."""
        if depth_m.shape != self.shape:
            return None
        sub = depth_m[:: self.stride, :: self.stride]
        valid = sub > 0
        count = int(valid.sum())
        if count == 0:
            return None
        return float((sub[valid] * self._factor[valid]).sum() / count)
