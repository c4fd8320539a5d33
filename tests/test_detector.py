"""The circle detector on frames rendered by sim/ (known truth) and on real RGB-D frames."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynqos.common.config import DetectorConfig
from dynqos.common.depthcodec import encode_zstd16
from dynqos.common.errors import DecodeError
from dynqos.common.messages import CameraFrame
from dynqos.edge.detector.circles import chroma, decode_depth, decode_rgb, find_circles, locate
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.render import Renderer
from dynqos.sim.vehicle.world import default_world

CFG = DetectorConfig()


def yaw_rot(yaw: float) -> np.ndarray:
    return quat_to_rot(np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]))


View = tuple[np.ndarray, np.ndarray, tuple[float, float], float, float, Renderer]


def rendered_hoop_views(count: int) -> list[View]:
    """Frames facing a hoop from 1.5-2.5 m, slightly off-axis; truth: the centre of the projected rim
    (an ellipse under perspective), the hoop's distance and its outer radius."""
    world = default_world()
    renderer = Renderer(world, seed=4)
    rng = np.random.default_rng(0)
    views = []
    for i in range(count):
        hoop = world.hoops[i % 2]
        n = np.array(hoop.normal) / np.linalg.norm(hoop.normal)
        a1 = np.cross(n, [0.0, 0.0, 1.0])
        a1 /= np.linalg.norm(a1)
        a2 = np.cross(n, a1)
        center = np.array(hoop.center_m)
        dist = rng.uniform(1.5, 2.5)  # the 7 x 7 m arena leaves no more room behind the camera
        pos = center - n * dist + a1 * rng.uniform(-0.3, 0.3) + np.array([0.0, 0.0, rng.uniform(-0.2, 0.2)])
        rot = yaw_rot(math.atan2(n[1], n[0]) + rng.uniform(-0.1, 0.1))
        rgb, depth = renderer.render(pos, rot)
        rim = []
        for t in np.linspace(0, 2 * math.pi, 90, endpoint=False):
            p = center + (hoop.radius_m + hoop.tube_m) * (math.cos(t) * a1 + math.sin(t) * a2)
            projected = renderer.project(p, pos, rot)
            assert projected is not None
            rim.append(projected[:2])
        (u, v), _, _ = cv2.fitEllipse(np.array(rim, np.float32))
        views.append((rgb, depth, (u, v), dist, hoop.radius_m + hoop.tube_m, renderer))
    return views


def test_chroma_is_the_spread_of_each_pixels_three_channels() -> None:
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    rgb[0, 0], rgb[0, 1], rgb[0, 2] = (0, 0, 0), (255, 0, 255), (7, 7, 7)
    spread = chroma(rgb)
    assert spread.dtype == np.uint8
    assert spread.shape == (48, 64)
    assert np.array_equal(spread, rgb.max(axis=2) - rgb.min(axis=2))
    assert list(spread[0, :3]) == [0, 255, 0]


def test_detector_finds_rendered_hoops() -> None:
    views = rendered_hoop_views(40)
    errors, false = [], 0
    for rgb, _, (u, v), _, _, _ in views:
        distances = [math.hypot(cu - u, cv - v) for cu, cv, _ in find_circles(rgb, CFG)]
        if distances and min(distances) <= 3.0:
            errors.append(min(distances))
        false += sum(1 for d in distances if d > 10)
    recall = len(errors) / len(views)
    print(f"recall {recall:.0%}, mean centre error {np.mean(errors):.2f} px, false circles {false}")
    assert recall >= 0.9
    assert false <= 2


def test_detected_hoops_are_located_in_3d_with_depth() -> None:
    for rgb, depth, (u, v), dist, outer_radius, renderer in rendered_hoop_views(6):
        circles = locate(find_circles(rgb, CFG), depth.astype(np.float32), renderer.intrinsics.as_tuple())
        best = min(circles, key=lambda c: math.hypot(c.u_px - u, c.v_px - v))
        assert best.center_m is not None
        _, _, z, radius = best.center_m
        assert z == pytest.approx(dist, abs=0.15)  # the ring's depth is the hoop's distance
        # the outer or the inner edge of the ring (tube 0.08 m)
        assert outer_radius - 0.16 - 0.05 <= radius <= outer_radius + 0.05
    assert locate([(10.0, 10.0, 5.0)], None, (525.0, 525.0, 319.5, 239.5))[0].center_m is None


def test_few_false_circles_on_real_frames(shared_data: Path) -> None:
    found = []
    for i in range(1, 6):
        rgb = cv2.cvtColor(cv2.imread(str(shared_data / "rgbd" / f"color_{i}.png")), cv2.COLOR_BGR2RGB)
        found.append(len(find_circles(rgb, CFG)))
    rate = sum(found) / len(found)
    print(f"false circles on the real RGB-D frames: {found} ({rate:.1f} per frame)")
    assert rate <= 2.0


def frame(kind: str, encoding: str, payload: bytes, width: int = 4, height: int = 2) -> CameraFrame:
    return CameraFrame(uav="u", seq=1, stamp_ns=1, kind=kind, encoding=encoding, width=width, height=height,
                       intrinsics=(1.0, 1.0, 0.0, 0.0), payload=payload)  # fmt: skip


def test_decoders_round_trip_and_reject_bad_payloads() -> None:
    depth = (np.arange(8, dtype=np.uint16) * 1000).reshape(2, 4)
    assert decode_depth(frame("depth", "zstd16", encode_zstd16(depth))) == pytest.approx(depth / 1000.0)
    assert decode_depth(frame("depth", "raw16", depth.astype("<u2").tobytes())) == pytest.approx(
        depth / 1000.0
    )
    ok, png = cv2.imencode(".png", depth)
    assert ok
    assert decode_depth(frame("depth", "png16", png.tobytes())) == pytest.approx(depth / 1000.0)
    rgb = np.zeros((2, 4, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)
    ok, jpg = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert np.array_equal(decode_rgb(frame("rgb", "png", jpg.tobytes())), rgb)
    assert np.array_equal(decode_rgb(frame("rgb", "raw8", rgb.tobytes())), rgb)
    for bad in (
        frame("rgb", "jpeg", b"not a jpeg"),
        frame("rgb", "raw8", b"\x00" * 5),
        frame("rgb", "png16", b""),
        frame("depth", "zstd16", b"garbage"),
        frame("depth", "raw16", b"\x00"),
        frame("depth", "png16", jpg.tobytes()),
        frame("depth", "png16", png.tobytes(), width=8),
        frame("depth", "jpeg", b""),
    ):
        decoder = decode_rgb if bad.kind == "rgb" else decode_depth
        with pytest.raises(DecodeError):
            decoder(bad)
    with pytest.raises(DecodeError, match="expected an rgb"):
        decode_rgb(frame("depth", "raw16", b""))
