"""Circle detection on RGB frames (OpenCV HoughCircles) and 3-D location with the depth frame. Pure.

A circle's centre pixel is back-projected with the depth of the ring around it (the centre of a hoop
is open, so the depth behind it says nothing about the hoop); the radius in metres follows from that
depth and the intrinsics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from dynqos.common.config import DetectorConfig
from dynqos.common.depthcodec import decode_zstd16
from dynqos.common.errors import DecodeError
from dynqos.common.messages import CameraFrame


@dataclass(frozen=True, slots=True)
class Circle:
    u_px: float
    v_px: float
    r_px: float
    center_m: tuple[float, float, float, float] | None  # x, y, z in the camera frame, radius (m)


def decode_rgb(frame: CameraFrame) -> NDArray[np.uint8]:
    if frame.kind != "rgb":
        raise DecodeError("kind", f"expected an rgb frame, got {frame.kind}")
    if frame.encoding in ("jpeg", "png"):
        image = cv2.imdecode(np.frombuffer(frame.payload, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise DecodeError("payload", f"not a decodable {frame.encoding} image")
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif frame.encoding == "raw8":
        expected = frame.width * frame.height * 3
        if len(frame.payload) != expected:
            raise DecodeError("payload", f"raw8 needs {expected} bytes, got {len(frame.payload)}")
        image = np.frombuffer(frame.payload, np.uint8).reshape(frame.height, frame.width, 3)
    else:
        raise DecodeError("encoding", f"{frame.encoding} is not an RGB encoding")
    if image.shape[:2] != (frame.height, frame.width):
        raise DecodeError(
            "payload", f"image is {image.shape[1]}x{image.shape[0]}, frame says {frame.width}x{frame.height}"
        )
    return np.asarray(image, dtype=np.uint8)


def decode_depth(frame: CameraFrame) -> NDArray[np.float32]:
    """Depth in metres (0 = no reading)."""
    if frame.kind != "depth":
        raise DecodeError("kind", f"expected a depth frame, got {frame.kind}")
    if frame.encoding == "png16":
        raw = cv2.imdecode(np.frombuffer(frame.payload, np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise DecodeError("payload", "not a 16-bit single-channel PNG")
    elif frame.encoding == "raw16":
        expected = frame.width * frame.height * 2
        if len(frame.payload) != expected:
            raise DecodeError("payload", f"raw16 needs {expected} bytes, got {len(frame.payload)}")
        raw = np.frombuffer(frame.payload, "<u2").reshape(frame.height, frame.width)
    elif frame.encoding == "zstd16":
        raw = decode_zstd16(frame.payload, frame.width, frame.height)
    else:
        raise DecodeError("encoding", f"{frame.encoding} is not a depth encoding")
    if raw.shape != (frame.height, frame.width):
        raise DecodeError(
            "payload", f"depth is {raw.shape[1]}x{raw.shape[0]}, frame says {frame.width}x{frame.height}"
        )
    depth: NDArray[np.float32] = raw.astype(np.float32) * np.float32(frame.depth_unit_m)
    return depth


def chroma(rgb: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """max(R, G, B) - min(R, G, B) per pixel, by OpenCV on the three planes: numpy's max over the last
    axis of a 640 x 480 image took 23 ms, most of a detection (now 2 ms in all); this 0.5 ms."""
    r, g, b = cv2.split(rgb)
    high = cv2.max(cv2.max(r, g), b)
    low = cv2.min(cv2.min(r, g), b)
    return np.asarray(cv2.subtract(high, low), dtype=np.uint8)


def find_circles(rgb: NDArray[np.uint8], cfg: DetectorConfig) -> list[tuple[float, float, float]]:
    # chroma: coloured markers stand out, grey walls, textures and shadows do not
    gray = chroma(rgb) if cfg.channel == "chroma" else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    if cfg.blur_px:
        gray = cv2.medianBlur(gray, cfg.blur_px)
    found = cv2.HoughCircles(
        gray,
        cv2.HOUGH_GRADIENT,
        dp=cfg.dp,
        minDist=cfg.min_dist_px,
        param1=cfg.canny_high,
        param2=cfg.accumulator,
        minRadius=cfg.min_radius_px,
        maxRadius=cfg.max_radius_px,
    )
    if found is None:
        return []
    edges = cv2.Canny(gray, cfg.canny_high / 2, cfg.canny_high)
    ys, xs = np.nonzero(edges)
    return [_refine(float(u), float(v), float(r), xs, ys) for u, v, r in found[0][: cfg.max_circles]]


def _refine(
    u: float, v: float, r: float, xs: NDArray[np.intp], ys: NDArray[np.intp]
) -> tuple[float, float, float]:
    """Hough's accumulator is coarse; fit a circle (least squares, Kasa) to the edge pixels near the
    one it found, for sub-pixel centres. Keeps the Hough circle when too few edge pixels support it."""
    dist = np.hypot(xs - u, ys - v)
    near = np.abs(dist - r) < max(4.0, 0.06 * r)
    if near.sum() < 30:
        return u, v, r
    x, y = xs[near].astype(float), ys[near].astype(float)
    a = np.column_stack([x, y, np.ones_like(x)])
    sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    cu, cv = sol[0] / 2, sol[1] / 2
    cr = math.sqrt(max(sol[2] + cu * cu + cv * cv, 0.0))
    if abs(cr - r) > 0.1 * r or math.hypot(cu - u, cv - v) > 0.1 * r:
        return u, v, r
    return float(cu), float(cv), float(cr)


def locate(
    circles: list[tuple[float, float, float]],
    depth_m: NDArray[np.float32] | None,
    intrinsics: tuple[float, float, float, float],
) -> list[Circle]:
    fx, fy, cx, cy = intrinsics
    out = []
    for u, v, r in circles:
        center = None
        if depth_m is not None:
            h, w = depth_m.shape
            # Sample just inside and just outside the detected edge: whichever side the ring is on, about
            # half the samples hit it and the rest the (farther) background, so take the near quartile.
            angles = np.linspace(0, 2 * math.pi, 48, endpoint=False)
            radii = r * np.array([0.9, 0.95, 1.05, 1.1])[:, None]
            us = np.clip(np.round(u + radii * np.cos(angles)).astype(int), 0, w - 1)
            vs = np.clip(np.round(v + radii * np.sin(angles)).astype(int), 0, h - 1)
            ring = depth_m[vs, us]
            ring = ring[ring > 0]
            if len(ring) >= 16:
                z = float(np.percentile(ring, 25))
                center = ((u - cx) / fx * z, (v - cy) / fy * z, z, r / fx * z)
        out.append(Circle(u, v, r, center))
    return out
