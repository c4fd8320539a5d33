from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynqos.onboard.risk import Spaciousness
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.render import Renderer
from dynqos.sim.vehicle.world import Arena, World, default_world

KINECT = (518.0, 519.0, 325.5, 253.5)


def test_flat_wall_spaciousness_is_the_mean_ray_length() -> None:
    s = Spaciousness(640, 480, (525.0, 525.0, 319.5, 239.5), stride=1)
    depth = np.full((480, 640), 4.0)
    u, v = np.meshgrid(np.arange(640), np.arange(480))
    expected = float(np.mean(4.0 * np.sqrt(1 + ((u - 319.5) / 525) ** 2 + ((v - 239.5) / 525) ** 2)))
    assert s(depth) == pytest.approx(expected, rel=1e-5)
    depth[:, :320] = 0.0  # no readings on the left half: left out, not counted as 0 m
    assert s(depth) == pytest.approx(
        float(np.mean((4.0 * np.sqrt(1 + ((u - 319.5) / 525) ** 2 + ((v - 239.5) / 525) ** 2))[:, 320:])),
        rel=1e-5,
    )
    assert s(np.zeros((480, 640))) is None
    assert s(np.zeros((10, 10))) is None
    with pytest.raises(ValueError, match="positive"):
        Spaciousness(640, 480, (0.0, 1.0, 0.0, 0.0))


def test_rendered_risk_zones_of_the_default_world() -> None:
    renderer = Renderer(default_world(), seed=2)
    s = Spaciousness(640, 480, renderer.intrinsics.as_tuple())

    def at(x: float, y: float, yaw: float) -> float:
        rot = quat_to_rot(np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]))
        _, depth = renderer.render(np.array([x, y, -1.5]), rot)
        value = s(depth)
        assert value is not None
        return value

    near_pillars = at(0.0, 2.0, math.pi / 2)  # facing the pillars from the circle
    open_space = at(-2.0, 0.0, 0.0)  # across the arena
    assert near_pillars <= 3.0  # high risk
    assert open_space > near_pillars + 1.0
    print(f"spaciousness: facing the pillars {near_pillars:.2f} m, open space {open_space:.2f} m")


def test_nothing_in_range_gives_no_spaciousness() -> None:
    empty = Renderer(World(arena=Arena(size_m=(40.0, 40.0, 40.0))), seed=1)
    s = Spaciousness(640, 480, empty.intrinsics.as_tuple())
    rot = quat_to_rot(np.array([1.0, 0.0, 0.0, 0.0]))
    assert s(empty.render(np.array([0.0, 0.0, -20.0]), rot)[1]) is None  # every wall beyond 10 m


def test_spaciousness_of_real_kinect_frames(shared_data: Path) -> None:
    s = Spaciousness(640, 480, KINECT)
    values = []
    for i in range(1, 6):
        raw = cv2.imread(str(shared_data / "rgbd" / f"depth_{i}.pgm"), cv2.IMREAD_UNCHANGED)
        assert raw is not None
        assert raw.dtype == np.uint16
        value = s(raw.astype(np.float32) / 1000.0)
        assert value is not None
        values.append(value)
    # An indoor scene a few metres deep: every frame between 1 and 6 m, consecutive frames close.
    assert all(1.0 < v < 6.0 for v in values), values
    assert max(values) - min(values) < 1.5
