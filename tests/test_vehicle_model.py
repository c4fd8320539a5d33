"""The simulated quadrotor and its PX4-like controller, stepped in lock-step (no sockets, deterministic)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dynqos.common.config import VehicleSimConfig
from dynqos.sim.vehicle.dynamics import GRAVITY, QuadParams, QuadState, quat_to_rot, rot_to_quat, yaw_of
from dynqos.sim.vehicle.model import VehicleModel
from dynqos.sim.vehicle.px4 import (
    MAIN_AUTO,
    MAIN_OFFBOARD,
    SUB_AUTO_LOITER,
    FlightController,
    Mode,
    Result,
    Setpoint,
)

SETPOINT_S = 0.02


def airborne(alt: float = 2.0, config: VehicleSimConfig | None = None) -> VehicleModel:
    model = VehicleModel(config)
    assert model.fc.arm(True, model.state, True, model.now_ns) is Result.ACCEPTED
    assert model.fc.takeoff(alt, model.state, model.now_ns) is Result.ACCEPTED
    model.advance(8.0)
    assert model.fc.mode is Mode.HOLD
    return model


def offboard(model: VehicleModel, setpoint: Setpoint) -> None:
    for _ in range(10):
        model.fc.on_setpoint(setpoint, model.now_ns)
        model.advance(SETPOINT_S)
    assert model.fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns) is Result.ACCEPTED


def fly(model: VehicleModel, setpoint: Setpoint, seconds: float) -> list[QuadState]:
    states = []
    for _ in range(round(seconds / SETPOINT_S)):
        model.fc.on_setpoint(setpoint, model.now_ns)
        states.append(model.advance(SETPOINT_S))
    return states


def test_takeoff_and_hover_holds_within_5_cm() -> None:
    model = airborne(2.0)
    errors = []
    for _ in range(500):  # 10 s
        state = model.advance(SETPOINT_S)
        errors.append(float(np.linalg.norm(state.pos_m - np.array([0.0, 0.0, -2.0]))))
    assert max(errors) < 0.05


def test_a_1_m_position_step_settles_with_at_most_20_percent_overshoot() -> None:
    model = airborne(2.0)
    offboard(model, Setpoint(pos_m=(0.0, 0.0, -2.0), yaw_rad=0.0))
    states = fly(model, Setpoint(pos_m=(1.0, 0.0, -2.0), yaw_rad=0.0), 8.0)
    xs = [s.pos_m[0] for s in states]
    assert max(xs) <= 1.2
    assert abs(xs[-1] - 1.0) < 0.05  # PX4 itself ended 0.02-0.04 m off (docs/simulator.md)
    assert all(abs(s.pos_m[2] + 2.0) < 0.1 for s in states)


def test_velocity_setpoints_are_tracked() -> None:
    model = airborne(2.0)
    offboard(model, Setpoint(vel_mps=(0.0, 0.0, 0.0), yaw_rad=0.0))
    states = fly(model, Setpoint(vel_mps=(1.0, -0.5, 0.0), yaw_rad=0.0), 8.0)
    # PX4's cascade against SIH's drag: P takes it to 80% within a second, then the integral closes
    # the rest slowly, as it does in PX4 (no drag feedforward there either).
    assert states[49].vel_mps[0] > 0.6
    assert states[-1].vel_mps == pytest.approx([1.0, -0.5, 0.0], abs=0.12)
    assert abs(states[-1].vel_mps[0] - 1.0) < abs(states[199].vel_mps[0] - 1.0)


def test_acceleration_setpoints_are_tracked() -> None:
    model = airborne(2.0)
    offboard(model, Setpoint(accel_mps2=(0.0, 0.0, 0.0), yaw_rad=0.0))
    v0 = model.state.vel_mps.copy()
    states = fly(model, Setpoint(accel_mps2=(1.0, 0.0, 0.0), yaw_rad=0.0), 1.0)
    # Linear drag (SIH's 1 /s) is the only other force: v(t) = a/d (1 - exp(-d t)) from rest.
    drag = model.params.drag_per_s[0]
    expected = 1.0 / drag * (1 - math.exp(-drag * 1.0))
    assert states[-1].vel_mps[0] - v0[0] == pytest.approx(expected, rel=0.1)
    assert abs(states[-1].pos_m[2] + 2.0) < 0.15


def test_yaw_setpoint_is_tracked() -> None:
    model = airborne(2.0)
    offboard(model, Setpoint(pos_m=(0.0, 0.0, -2.0), yaw_rad=0.0))
    fly(model, Setpoint(pos_m=(0.0, 0.0, -2.0), yaw_rad=1.0), 4.0)
    assert yaw_of(model.state.quat) == pytest.approx(1.0, abs=0.02)


def test_offboard_is_refused_without_a_setpoint_stream() -> None:
    model = airborne(2.0)
    assert model.fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns) is Result.TEMPORARILY_REJECTED
    model.fc.on_setpoint(Setpoint(pos_m=(0.0, 0.0, -2.0)), model.now_ns)
    assert model.fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns) is Result.TEMPORARILY_REJECTED
    assert model.fc.mode is Mode.HOLD


def test_failsafe_holds_position_1_s_after_setpoints_stop() -> None:
    model = airborne(2.0)
    offboard(model, Setpoint(pos_m=(0.0, 0.0, -2.0), yaw_rad=0.0))
    fly(model, Setpoint(vel_mps=(1.0, 0.0, 0.0), yaw_rad=0.0), 2.0)
    stopped_at = model.now_ns
    while model.fc.mode is Mode.OFFBOARD:
        model.advance(0.005)
    assert (model.now_ns - stopped_at) / 1e9 == pytest.approx(1.0, abs=0.02)
    assert model.fc.mode is Mode.HOLD
    held = model.fc.hold_pos
    assert held is not None
    model.advance(5.0)
    assert np.linalg.norm(model.state.pos_m - held) < 0.6  # it brakes from 1 m/s and returns
    assert np.linalg.norm(model.state.vel_mps) < 0.05
    assert "offboard lost: holding position" in model.fc.events


def test_land_disarms_on_the_ground_and_disarm_in_flight_is_denied() -> None:
    model = airborne(2.0)
    assert model.fc.arm(False, model.state, model.plant.on_ground, model.now_ns) is Result.DENIED
    assert model.fc.land(model.state) is Result.ACCEPTED
    model.advance(6.0)
    assert model.plant.on_ground
    assert not model.fc.armed
    assert model.fc.takeoff(2.0, model.state, model.now_ns) is Result.DENIED


def test_modes_and_custom_mode_encoding() -> None:
    assert Mode.OFFBOARD.custom_mode == 6 << 16
    assert Mode.HOLD.custom_mode == (4 << 16) | (3 << 24)
    assert Mode.from_custom(MAIN_AUTO, SUB_AUTO_LOITER) is Mode.HOLD
    assert Mode.from_custom(MAIN_OFFBOARD, 7) is Mode.OFFBOARD
    assert Mode.from_custom(42, 0) is None
    model = airborne(2.0)
    assert model.fc.set_mode(42, 0, model.state, model.now_ns) is Result.UNSUPPORTED
    assert model.fc.takeoff(500.0, model.state, model.now_ns) is Result.DENIED


def test_setpoint_type_mask() -> None:
    sp = Setpoint.from_mavlink(0b110111111000 & ~1024, (1, 2, 3), (4, 5, 6), (7, 8, 9), 0.5)
    assert sp == Setpoint(pos_m=(1, 2, 3), vel_mps=None, accel_mps2=None, yaw_rad=0.5)
    only_accel = Setpoint.from_mavlink(0b0000_1100_0011_1111, (0, 0, 0), (0, 0, 0), (1, 0, 0), 0.0)
    assert only_accel is not None
    assert only_accel.accel_mps2 == (1, 0, 0)
    assert only_accel.pos_m is None
    assert only_accel.yaw_rad is None
    assert Setpoint.from_mavlink(0xFFFF, (0, 0, 0), (0, 0, 0), (0, 0, 0), 0.0) is None
    assert Setpoint.from_mavlink(0, (math.nan, 0, 0), (0, 0, 0), (0, 0, 0), 0.0) is None


def test_wind_gusts_are_reproducible_for_a_seed() -> None:
    runs = []
    for _ in range(2):
        model = airborne(2.0, VehicleSimConfig(wind_mps=(2.0, 0.0, 0.0), gust_std_mps=1.0, seed=5))
        model.advance(3.0)
        runs.append(model.state.pos_m.copy())
    assert np.array_equal(runs[0], runs[1])
    assert np.linalg.norm(runs[0] - np.array([0, 0, -2.0])) < 0.5  # the controller holds against wind


def test_rotation_helpers_round_trip() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= 1 if q[0] >= 0 else -1
        assert rot_to_quat(quat_to_rot(q)) == pytest.approx(q, abs=1e-9)


def test_world_collision_names_what_a_sphere_touches() -> None:
    from dynqos.sim.vehicle.world import Box, Cylinder, Hoop, World, collision

    world = World(
        boxes=(Box(min_m=(1.0, 1.0, -1.0), max_m=(2.0, 2.0, 0.0)),),
        cylinders=(Cylinder(center_m=(-2.0, 0.0), radius_m=0.3, z_top_m=-2.0),),
        hoops=(Hoop(center_m=(0.0, -2.0, -1.5), radius_m=0.5, normal=(1.0, 0.0, 0.0)),),
    )
    assert collision(world, (0.0, 0.0, -1.5)) is None
    assert collision(world, (1.5, 0.9, -0.5)) == "box 0"  # 0.1 m from its face, radius 0.15
    assert collision(world, (1.5, 0.8, -0.5)) is None
    assert collision(world, (-1.6, 0.0, -1.0)) == "cylinder 0"
    assert collision(world, (-2.0, 0.0, -2.5)) is None  # above its top
    assert collision(world, (0.0, -2.5, -1.5)) == "hoop 0"  # on the ring
    assert collision(world, (0.0, -2.0, -1.5)) is None  # through its middle
    assert collision(world, (3.45, 0.0, -1.0)) == "arena wall"
    assert collision(world, (0.0, 0.0, -2.9)) == "arena ceiling"


def _attitude_by_matrices(fc: FlightController, state: QuadState, accel: np.ndarray, yaw: float) -> tuple:
    """Lee et al.'s geometric controller written with numpy matrices, as the paper writes it: the
    reference the flight controller's plain-float version must match."""
    p, g = fc.params, fc.gains
    norm = float(np.linalg.norm(accel))
    if norm > g.accel_max_mps2:
        accel = accel * (g.accel_max_mps2 / norm)
    thrust_vec = p.mass_kg * (accel - np.array([0.0, 0.0, GRAVITY]))
    thrust_vec[2] = min(thrust_vec[2], -0.2 * p.mass_kg * GRAVITY)
    z_body = -thrust_vec / np.linalg.norm(thrust_vec)
    if math.acos(max(-1.0, min(1.0, z_body[2]))) > g.tilt_max_rad:
        horizontal = np.array([z_body[0], z_body[1], 0.0])
        horizontal /= max(np.linalg.norm(horizontal), 1e-9)
        z_body = horizontal * math.sin(g.tilt_max_rad) + np.array([0.0, 0.0, math.cos(g.tilt_max_rad)])
    y_body = np.cross(z_body, [math.cos(yaw), math.sin(yaw), 0.0])
    y_body /= max(float(np.linalg.norm(y_body)), 1e-9)
    r_des = np.column_stack([np.cross(y_body, z_body), y_body, z_body])
    rot = quat_to_rot(state.quat)
    e_mat = r_des.T @ rot - rot.T @ r_des
    e_rot = 0.5 * np.array([e_mat[2, 1], e_mat[0, 2], e_mat[1, 0]])
    inertia, wn = np.array(p.inertia), np.array([g.att_wn, g.att_wn, g.yaw_wn])
    rates = state.rates_rps
    torque = (
        -inertia * wn**2 * e_rot - inertia * 2 * g.att_zeta * wn * rates + np.cross(rates, inertia * rates)
    )
    return float(-thrust_vec @ rot[:, 2]), torque


def test_the_attitude_controller_matches_its_matrix_form_on_random_states() -> None:
    rng = np.random.default_rng(7)
    fc = FlightController(QuadParams())
    for _ in range(2000):
        quat = rng.normal(size=4)
        state = QuadState(quat=quat / np.linalg.norm(quat), rates_rps=rng.normal(size=3))
        accel = rng.normal(size=3) * rng.choice([0.1, 3.0, 30.0])  # gentle, tilted past the limit, capped
        yaw = float(rng.uniform(-4, 4))
        thrust, torque = fc._attitude(state, accel, yaw)
        want_thrust, want_torque = _attitude_by_matrices(fc, state, accel, yaw)
        assert thrust == pytest.approx(want_thrust, abs=1e-9)
        np.testing.assert_allclose(torque, want_torque, atol=1e-9)
