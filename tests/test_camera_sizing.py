"""The camera is sized on the views the scenario flies, and the cell's hidden socket buffers scale."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from dynqos.common.config import ZenohConfig
from dynqos.common.geometry import yaw_of
from dynqos.plan.camera_sizing import attitude, flight_views, frame_bits
from dynqos.plan.scenario import builtin_scenario, scenario_config
from dynqos.sim.network.bearer import MIN_SOCKET_BUFFER, SOCKET_BUFFER, socket_buffer_bytes


def tilt_of(quat: tuple[float, float, float, float]) -> float:
    """The angle between the body's down axis and the world's."""
    _, x, y, _ = quat
    return math.acos(max(-1.0, min(1.0, 1 - 2 * (x * x + y * y))))


def config_for(name: str, scale: float = 10.0):  # type: ignore[no-untyped-def]
    scenario = replace(builtin_scenario(name), scale=scale)
    return scenario_config(scenario, zenoh=ZenohConfig(), fc_port=14601, gcs_port=14602)


def test_a_hovering_drone_is_sized_level_at_its_hover_point_facing_its_take_off_heading() -> None:
    views = flight_views(config_for("bg-noqos"))  # the no-QoS scenario hovers
    assert {pos for pos, _ in views} == {(0.0, 0.0, -1.5)}
    assert all(tilt_of(q) < 1e-6 and abs(yaw_of(q)) < 1e-6 for _, q in views)


def test_the_circle_is_sized_tilted_by_its_centripetal_acceleration() -> None:
    views = flight_views(config_for("baseline"))
    centripetal = 2.0 * (2 * math.pi / 10.0) ** 2  # radius 2 m, period 10 s
    for pos, quat in views:
        assert math.hypot(pos[0], pos[1]) == pytest.approx(2.0, abs=1e-6)
        assert tilt_of(quat) == pytest.approx(math.atan(centripetal / 9.81), abs=1e-3)
        assert yaw_of(quat) == pytest.approx(0.0, abs=0.01)  # yaw = "free": the heading is held


def test_attitude_leans_into_the_acceleration() -> None:
    quat = attitude([2.0, 0.0, 0.0], 0.0)  # accelerate north, facing north: nose down
    w, x, y, z = quat
    nose_z = 2 * (x * z - w * y)  # the body x axis's down component
    assert nose_z > 0.1
    assert tilt_of(quat) == pytest.approx(math.atan(2.0 / 9.81), abs=1e-6)


@pytest.mark.parametrize("name", ["baseline", "bg-noqos"])
def test_every_scenario_offers_its_rate_from_its_own_views(name: str) -> None:
    config = config_for(name)
    scenario = builtin_scenario(name)
    offered = frame_bits(
        config.onboard.camera_width, config.onboard.camera_height, flight_views(config),
        config.onboard.camera_part_bytes,
    ) * scenario.camera_fps * scenario.scale  # fmt: skip
    assert offered == pytest.approx(scenario.uav_mbps * 1e6, rel=0.05)


def test_socket_buffers_hold_the_same_time_at_every_scale() -> None:
    assert socket_buffer_bytes(1.0) == SOCKET_BUFFER
    assert socket_buffer_bytes(10.0) == round(SOCKET_BUFFER / 10)
    assert socket_buffer_bytes(1000.0) == MIN_SOCKET_BUFFER
    assert config_for("bg-noqos", 10.0).zenoh.bulk_sndbuf_bytes == socket_buffer_bytes(10.0)
    assert config_for("bg-noqos", 1.0).zenoh.bulk_sndbuf_bytes == SOCKET_BUFFER
