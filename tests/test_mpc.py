"""The edge MPC as pure logic: closed-loop tracking, delay compensation, constraints, an independent solve."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from dynqos.common.config import ControlConfig, MpcConfig
from dynqos.common.messages import OFFBOARD, STANDING_BY, Reference, State
from dynqos.common.modes import ControlSource
from dynqos.common.reference import ReferenceTrack
from dynqos.edge.mpc.controller import DroneController
from dynqos.edge.mpc.problem import MpcProblem, SolveError, discretise
from dynqos.edge.planner.missions import Mission, load_waypoints
from tests.closedloop import fly_circle


def state(
    seq: int, pos: tuple[float, float, float] = (0.0, 0.0, -1.5), rtt_ms: float = 0.0, stamp_ns: int = 0
) -> State:
    return State(
        uav="uav1",
        seq=seq,
        stamp_ns=stamp_ns or seq * 50_000_000,
        pos_m=pos,
        vel_mps=(0.0, 0.0, 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        rtt_est_ms=rtt_ms,
    )


@pytest.mark.parametrize("qos", ["dynamic", "default", "priority"])
def test_closed_loop_tracks_a_2_m_10_s_circle(qos: str) -> None:
    """The onboard core, the MPC service and the vehicle model over an in-memory bus with 20 ms RTT."""
    flight = fly_circle(rtt_ms=20.0, qos=qos)
    print(f"qos {qos}: circle RMSE after the first lap: {flight.rmse_m * 100:.1f} cm; ticks {flight.sources}")
    assert flight.rmse_m < 0.10
    limits = np.array(MpcConfig().a_max_mps2)
    assert all(np.all(np.abs(np.array(c.accel_mps2)) <= limits + 1e-9) for c in flight.commands)
    # The edge flew the measured lap alone; the one fallback was the start, before the first command.
    assert set(flight.sources) == {ControlSource.EDGE}
    assert flight.core is not None
    assert flight.core.counters.switches_to_fallback <= 1


def test_delay_compensation_beats_no_compensation_at_100_ms() -> None:
    with_comp = fly_circle(rtt_ms=100.0, mpc=MpcConfig(compensate_delay=True))
    without = fly_circle(rtt_ms=100.0, mpc=MpcConfig(compensate_delay=False))
    print(f"100 ms RTT: RMSE {with_comp.rmse_m:.3f} m with compensation, {without.rmse_m:.3f} m without")
    assert with_comp.rmse_m < without.rmse_m


def test_solution_respects_every_constraint() -> None:
    settings = MpcConfig()
    problem = MpcProblem(settings, ControlConfig(horizon=30))
    rng = np.random.default_rng(1)
    for _ in range(30):
        x0 = np.concatenate([rng.uniform(-3, 3, 3), rng.uniform(-1, 1, 3)])
        target = rng.uniform(-20, 20, 3)  # far away: the limits bind
        reference = np.tile(np.concatenate([target, np.zeros(3)]), (31, 1))
        inputs = problem.solve(x0, reference)
        assert np.all(np.abs(inputs) <= np.array(settings.a_max_mps2) + 1e-6)
        states = problem.predict(x0, inputs)
        assert np.all(np.abs(states[1:, 3:]) <= np.array(settings.v_max_mps) + 2e-3)


def test_a_drone_faster_than_v_max_gets_a_braking_plan_not_an_infeasible_qp() -> None:
    """After a gust or the fallback, the measured velocity may exceed v_max: the MPC must still answer
    (an infeasible QP sends nothing, and the watchdog would take over again and again)."""
    settings = MpcConfig()
    problem = MpcProblem(settings)
    v_max = np.array(settings.v_max_mps)
    x0 = np.array([0.0, 0.0, -1.5, 4.0, -3.5, 2.5])  # over the limit on every axis
    reference = np.tile([0.0, 0.0, -1.5, 0, 0, 0], (21, 1))
    inputs = problem.solve(x0, reference)
    assert inputs[0] @ np.sign(x0[3:]) < 0  # braking on every axis together
    speeds = np.abs(problem.predict(x0, inputs)[:, 3:])
    assert np.all(np.diff(np.maximum(speeds - v_max, 0), axis=0) <= 1e-6)  # the excess only shrinks
    assert np.all(speeds[-1] <= v_max + 1e-3)  # and is gone by the end of the horizon


def test_first_input_matches_an_independent_solve_of_the_same_qp() -> None:
    cp = pytest.importorskip("cvxpy")
    settings = MpcConfig(eps=1e-7, max_iter=20_000)
    problem = MpcProblem(settings, ControlConfig(horizon=20))
    x0 = np.array([0.3, -0.2, -1.0, 0.5, 0.1, 0.0])
    t = np.arange(21) * problem.dt_s
    reference = np.column_stack(
        [2 * np.cos(t), 2 * np.sin(t), np.full(21, -1.5), -2 * np.sin(t), 2 * np.cos(t), np.zeros(21)]
    )
    ours = problem.solve(x0, reference)
    # The same QP written independently in cvxpy and solved by an interior-point solver (Clarabel).
    ad, bd = discretise(problem.dt_s, settings.drag_per_s)
    q = np.diag([settings.q_pos] * 3 + [settings.q_vel] * 3)
    x = cp.Variable((21, 6))
    u = cp.Variable((20, 3))
    cost = sum(
        cp.quad_form(x[k] - reference[k], q) + settings.r_acc * cp.sum_squares(u[k]) for k in range(20)
    )
    cost += settings.terminal_factor * cp.quad_form(x[20] - reference[20], q)
    constraints = [x[0] == x0]
    constraints += [x[k + 1] == ad @ x[k] + bd @ u[k] for k in range(20)]
    constraints += [
        cp.abs(x[:, 3:]) <= np.array(settings.v_max_mps),
        cp.abs(u) <= np.array(settings.a_max_mps2),
    ]
    cp.Problem(cp.Minimize(cost), constraints).solve(solver=cp.CLARABEL, canon_backend=cp.SCIPY_CANON_BACKEND)
    assert ours[0] == pytest.approx(u.value[0], abs=1e-4)


def test_solve_errors_are_raised_not_sent() -> None:
    problem = MpcProblem(MpcConfig(max_iter=10, eps=1e-8))
    reference = np.tile([5.0, 5.0, -1.5, 0, 0, 0], (21, 1))
    with pytest.raises(SolveError):
        problem.solve(np.zeros(6), reference)
    with pytest.raises(SolveError, match="non-finite"):
        MpcProblem().solve(np.array([math.nan, 0, 0, 0, 0, 0]), reference)
    with pytest.raises(ValueError, match="shape"):
        MpcProblem().solve(np.zeros(6), reference[:5])


def test_stale_states_are_ignored_and_no_reference_holds_position() -> None:
    ctrl = DroneController("uav1")
    plan = ctrl.step(state(5, pos=(1.0, 2.0, -1.5)), 0)
    assert plan is not None
    assert ctrl.step(state(5), 0) is None
    assert ctrl.step(state(4), 0) is None
    assert ctrl.stale == 2
    assert np.allclose(plan.accel_mps2[0], 0.0, atol=1e-3)  # already at the held position
    plan = ctrl.step(state(6, pos=(0.0, 2.0, -1.5)), 0)
    assert plan is not None
    assert plan.accel_mps2[0][0] > 0.5  # pulled back towards x = 1 m


def test_with_no_reference_the_hold_follows_a_climbing_drone_and_stays_where_it_went_offboard() -> None:
    ctrl = DroneController("uav1")
    for seq, down in enumerate((0.0, -0.5, -1.0, -1.5), start=1):  # standing, then climbing
        plan = ctrl.step(replace(state(seq, pos=(1.0, 2.0, down)), mode=STANDING_BY), 0)
        assert plan is not None
        assert np.allclose(plan.accel_mps2[0], 0.0, atol=1e-3)  # never pulled back to the ground
    plan = ctrl.step(replace(state(5, pos=(0.0, 2.0, -1.5)), mode=OFFBOARD), 0)
    assert plan is not None
    assert plan.accel_mps2[0][0] > 0.5  # offboard: held where the climb ended, 1 m ahead
    plan = ctrl.step(replace(state(6, pos=(0.0, 2.0, -1.5)), mode=STANDING_BY), 0)
    assert plan is not None
    assert np.allclose(plan.accel_mps2[0], 0.0, atol=1e-3)  # landed and standing by: follows again


def test_commands_carry_committed_inputs_for_the_rtt() -> None:
    ctrl = DroneController("uav1", MpcConfig(command_steps=10))
    for seq in range(1, 6):
        plan = ctrl.step(state(seq, rtt_ms=100.0), seq * 50_000_000)
        assert plan is not None
    assert plan.committed_steps == 2
    assert len(plan.accel_mps2) == 12
    assert plan.state_stamp_ns == 5 * 50_000_000
    assert plan.dt_s == 0.05


def test_reference_track_interpolates_and_holds_the_end() -> None:
    track = ReferenceTrack()
    assert track.window(0, 3, 0.05) is None
    ref = Reference(
        uav="u",
        seq=2,
        stamp_ns=0,
        dt_s=0.1,
        pos_m=[(0, 0, 0), (1, 0, 0)],
        vel_mps=[(10, 0, 0)] * 2,
        yaw_rad=[0.0, 1.0],
    )
    assert track.update(ref, 1_000_000_000)
    assert not track.update(ref, 2_000_000_000)  # same seq: not newer
    window = track.window(1_000_000_000, 4, 0.05)
    assert window is not None
    states, yaws = window
    assert states[:, 0] == pytest.approx([0.0, 0.5, 1.0, 1.0])
    assert states[3, 3] == 0.0  # past the end: hold, no velocity
    assert list(yaws) == [0.0, 1.0, 1.0, 1.0]


def test_missions(tmp_path: object) -> None:
    circle = Mission(kind="circle", radius_m=2.0, period_s=8.0, lead_in_s=2.0, altitude_m=1.5)
    p, v, yaw = circle.sample(0.0)
    assert p == pytest.approx((2.0, 0.0, -1.5))
    assert v == (0.0, 0.0, 0.0)  # lead-in: go to the start and wait
    p, v, yaw = circle.sample(4.0)  # a quarter lap in
    assert p == pytest.approx((0.0, 2.0, -1.5), abs=1e-9)
    assert yaw == pytest.approx(math.pi)  # tangent, counter-clockwise
    eight = Mission(kind="figure8", lead_in_s=0.0)
    assert eight.sample(0.0)[0] == pytest.approx((0.0, 0.0, -1.5))
    hover = Mission(kind="hover", center_m=(1.0, 1.0), altitude_m=2.0)
    assert hover.sample(100.0)[0] == (1.0, 1.0, -2.0)
    path = __import__("pathlib").Path(str(tmp_path)) / "w.txt"
    path.write_text("# x y z\n0 0 -1\n2 0 -1\n\n2 2 -1\n")
    wp = Mission(kind="waypoints", waypoints=load_waypoints(path), lead_in_s=0.0, speed_mps=1.0)
    assert wp.sample(1.0)[0] == pytest.approx((1.0, 0.0, -1.0))
    assert wp.sample(3.0)[0] == pytest.approx((2.0, 1.0, -1.0))
    assert wp.sample(10.0)[0] == (2.0, 2.0, -1.0)
    positions, velocities, yaws = circle.samples(2.0, 0.5, 4)
    assert len(positions) == len(velocities) == len(yaws) == 4
