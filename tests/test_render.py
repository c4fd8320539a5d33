"""The world file and the ray-caster: analytic depths, projected hoops, noise like a sensor's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dynqos.common.errors import ConfigError
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.render import DepthNoise, Intrinsics, Renderer
from dynqos.sim.vehicle.world import Arena, Box, Hoop, World, default_world, load_world


def yaw_rot(yaw: float) -> np.ndarray:
    return quat_to_rot(np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]))


def test_a_wall_at_9_m_reads_9_m() -> None:
    renderer = Renderer(World(arena=Arena(size_m=(20.0, 20.0, 6.0))), seed=1)
    _, depth = renderer.render(np.array([1.0, 0.0, -3.0]), yaw_rot(0.0))
    centre = depth[200:280, 280:360]
    valid = centre[centre > 0]
    assert len(valid) > 0.9 * centre.size  # ~2% dropouts
    assert float(np.median(valid)) == pytest.approx(9.0, abs=0.02)
    assert float(np.std(valid)) == pytest.approx(0.0012 * 81, rel=0.3)  # sigma = k z^2


def test_depth_is_along_the_optical_axis_and_exact_without_noise() -> None:
    renderer = Renderer(World(arena=Arena(size_m=(12.0, 12.0, 6.0))))
    _, depth = renderer.render(np.array([0.0, 0.0, -3.0]), yaw_rot(0.0), noisy=False)
    assert np.allclose(depth[100:380, 100:540], 6.0, atol=1e-4)  # a flat wall: the same z everywhere
    _, turned = renderer.render(np.array([0.0, 0.0, -3.0]), yaw_rot(math.pi / 2), noisy=False)
    assert turned[240, 320] == pytest.approx(6.0, abs=1e-4)


def test_a_box_in_front_is_nearer() -> None:
    world = World(
        arena=Arena(size_m=(20.0, 20.0, 6.0)), boxes=(Box(min_m=(3.0, -1.0, -5.0), max_m=(4.0, 1.0, 0.0)),)
    )
    _, depth = Renderer(world).render(np.array([0.0, 0.0, -3.0]), yaw_rot(0.0), noisy=False)
    assert depth[240, 320] == pytest.approx(3.0, abs=1e-4)
    assert depth[240, 5] == pytest.approx(10.0, abs=1e-3) or depth[240, 5] == 0.0  # beside the box: the wall


def test_hoops_appear_where_the_projection_says() -> None:
    hoop = Hoop(
        center_m=(2.0, 0.0, -1.5), radius_m=0.6, tube_m=0.05, normal=(0.0, 1.0, 0.0), color=(240, 140, 20)
    )
    world = World(hoops=(hoop,))
    renderer = Renderer(world, render_size=(320, 240))
    pos, rot = np.array([2.0, -2.0, -1.5]), yaw_rot(math.pi / 2)
    rgb, depth = renderer.render(pos, rot, noisy=False)
    u, v, z = renderer.project(np.array(hoop.center_m), pos, rot) or (0, 0, 0)
    assert (u, v, z) == pytest.approx((319.5, 239.5, 2.0), abs=1e-6)
    radius_px = renderer.intrinsics.fx * hoop.radius_m / z
    hits = 0
    for angle in np.linspace(0, 2 * math.pi, 36, endpoint=False):
        x, y = round(u + radius_px * math.cos(angle)), round(v + radius_px * math.sin(angle))
        pixel = rgb[y, x].astype(int)
        hits += int(abs(pixel[0] - pixel[2]) > 60 and depth[y, x] == pytest.approx(2.0, abs=0.05))
    assert hits >= 32  # orange ring at 2 m on the projected circle
    assert abs(int(rgb[round(v), round(u), 0]) - int(rgb[round(v), round(u), 2])) < 60  # the middle is open
    assert renderer.project(np.array([0.0, -5.0, -1.5]), pos, rot) is None  # behind the camera


def test_rendered_frames_have_sensor_like_noise_and_range() -> None:
    renderer = Renderer(default_world(), noise=DepthNoise(max_range_m=4.0, dropout=0.05), seed=3)
    rgb, depth = renderer.render(np.array([0.0, -2.0, -1.5]), yaw_rot(0.0))
    assert rgb.shape == (480, 640, 3)
    assert rgb.dtype == np.uint8
    assert depth.shape == (480, 640)
    assert depth.max() <= 4.0
    assert 0.05 < float((depth == 0).mean()) < 0.99  # dropouts plus everything beyond 4 m
    assert depth.max() > 3.0
    assert rgb.std() > 5  # textured enough to compress like an image


def test_intrinsics_scale() -> None:
    k = Intrinsics().scaled(160, 120)
    assert (k.fx, k.cx) == pytest.approx((131.25, 79.5))
    assert k.ray_directions().shape == (120, 160, 3)


def test_world_files(tmp_path: Path) -> None:
    path = tmp_path / "w.toml"
    path.write_text("[arena]\nsize_m = [8, 6, 3]\n[[hoops]]\ncenter_m = [1, 0, -1.5]\nradius_m = 0.5\n")
    world = load_world(path)
    assert world.arena.size_m == (8.0, 6.0, 3.0)
    assert world.hoops[0].radius_m == 0.5
    json_path = tmp_path / "w.json"
    json_path.write_text('{"boxes": [{"min_m": [0, 0, -1], "max_m": [1, 1, 0]}]}')
    assert len(load_world(json_path).boxes) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text("[[boxes]]\nmin_m = [0, 0, 0]\nmax_m = [1, 1, -1]\n")
    with pytest.raises(ConfigError, match=r"bad.toml: boxes\[0\].max_m: must exceed min_m"):
        load_world(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_world(tmp_path / "missing.toml")
    (tmp_path / "x.json").write_text("[1]")
    with pytest.raises(ConfigError, match="is a table"):
        load_world(tmp_path / "x.json")
    assert len(default_world().hoops) == 2
