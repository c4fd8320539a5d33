"""The fleet's MPC problems solved together (edge/mpc/batch.py): the unbounded optimum where no bound
binds, OSQP where one does, against OSQP on the states of a closed-loop flight."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from dynqos.common.config import ControlConfig, MpcConfig
from dynqos.edge.mpc.batch import BatchSolver, UnboundedOptimum
from dynqos.edge.mpc.problem import Array, MpcProblem, SolveError
from tests.closedloop import fly_circle

# The batched answer's first input beside OSQP's on the same QP, m/s^2 on any axis (docs/edge.md,
# "Batched solves"): OSQP at the MPC's own eps (1e-4), and OSQP solving tightly (eps 1e-7), which the
# drones left to OSQP at eps 1e-4 differ from by that eps's worth.
TOLERANCE = 1e-3


class RecordingSolver(BatchSolver):
    """Keeps every (initial state, reference) it was given and what it answered."""

    def __init__(self, batched: bool = True) -> None:
        super().__init__(batched)
        self.solved: list[tuple[Array, Array, Array]] = []

    def solve(
        self, problems: list[MpcProblem], x0: list[Array], references: list[Array]
    ) -> list[Array | SolveError]:
        results = super().solve(problems, x0, references)
        for x, r, answer in zip(x0, references, results, strict=True):
            if not isinstance(answer, SolveError):
                self.solved.append((x.copy(), r.copy(), answer.copy()))
        return results


def hold(x0: Array, target: Array, horizon: int = 20) -> Array:
    return np.tile(np.concatenate([target, np.zeros(3)]), (horizon + 1, 1))


def test_a_circle_flight_solved_in_batches_matches_osqp_on_every_state() -> None:
    solver = RecordingSolver()
    flight = fly_circle(rtt_ms=20.0, solver=solver)
    assert flight.rmse_m < 0.10
    c = solver.counters
    print(f"circle: {c.exact} exact, {c.iterative} by OSQP; RMSE {flight.rmse_m * 100:.1f} cm")
    assert c.exact > 0.9 * (c.exact + c.iterative)  # a cruising drone's bounds rarely bind
    tight = MpcProblem(MpcConfig(eps=1e-7, max_iter=50_000))
    default = MpcProblem(MpcConfig())
    worst_tight = worst_default = 0.0
    for x0, reference, answer in solver.solved:
        worst_tight = max(worst_tight, float(np.max(np.abs(tight.solve(x0, reference)[0] - answer[0]))))
        worst_default = max(worst_default, float(np.max(np.abs(default.solve(x0, reference)[0] - answer[0]))))
    print(f"first input vs OSQP: {worst_tight:.2e} (eps 1e-7), {worst_default:.2e} (eps 1e-4) m/s^2")
    assert worst_tight <= TOLERANCE
    assert worst_default <= TOLERANCE


def test_the_circle_tracks_as_well_batched_as_one_by_one() -> None:
    batched = fly_circle(rtt_ms=20.0, mpc=MpcConfig(batch_solves=True))
    one_by_one = fly_circle(rtt_ms=20.0, mpc=MpcConfig(batch_solves=False))
    assert batched.service is not None
    assert one_by_one.service is not None
    assert batched.service.solver.counters.exact > 0
    assert one_by_one.service.solver.counters.exact == 0
    print(f"RMSE batched {batched.rmse_m * 100:.2f} cm, one by one {one_by_one.rmse_m * 100:.2f} cm")
    assert batched.rmse_m < 0.10
    assert one_by_one.rmse_m < 0.10
    assert batched.rmse_m == pytest.approx(one_by_one.rmse_m, abs=0.005)


def test_only_the_drones_whose_bounds_bind_go_to_osqp_and_they_get_osqp_s_answer() -> None:
    settings = MpcConfig()
    problems = [MpcProblem(settings) for _ in range(4)]
    x0 = [
        np.array([0.0, 0.0, -1.5, 0.0, 0.0, 0.0]),  # holding: nothing binds
        np.array([0.1, -0.1, -1.4, 0.2, 0.0, 0.0]),  # near its hold: nothing binds
        np.array([0.0, 0.0, -1.5, 0.0, 0.0, 0.0]),  # 15 m to go: the acceleration limit binds
        np.array([0.0, 0.0, -1.5, 4.5, 0.0, 0.0]),  # faster than v_max: its funnel binds
    ]
    targets = [x0[0][:3], np.array([0.0, 0.0, -1.5]), np.array([15.0, 0.0, -1.5]), np.array([0.0, 0.0, -1.5])]
    references = [hold(x, t) for x, t in zip(x0, targets, strict=True)]
    solver = BatchSolver()
    answers = solver.solve(problems, x0, references)
    assert (solver.counters.exact, solver.counters.iterative) == (2, 2)
    alone = [MpcProblem(settings) for _ in range(4)]
    limits = np.array(settings.a_max_mps2)
    for i, answer in enumerate(answers):
        assert not isinstance(answer, SolveError)
        assert np.all(np.abs(answer) <= limits)  # input bounds hold exactly, batched or not
        expected = alone[i].solve(x0[i], references[i])
        assert answer[0] == pytest.approx(expected[0], abs=TOLERANCE)
    assert np.max(np.abs(answers[2])) == pytest.approx(limits[0])  # it did bind


def test_the_unbounded_optimum_is_the_qp_s_own_where_nothing_binds() -> None:
    """Checked on the QP's optimality conditions, not against another solver: the gradient of the cost
    in the inputs (the dynamics substituted) is zero."""
    problem = MpcProblem(MpcConfig(), ControlConfig(horizon=15))
    optimum = UnboundedOptimum(problem)
    rng = np.random.default_rng(3)
    x0 = np.column_stack([rng.normal(0, 0.2, (8, 3)), rng.normal(0, 0.1, (8, 3))])
    references = np.stack([hold(x, x[:3] + 0.1, 15) for x in x0])
    inputs, inside = optimum.solve(x0, references)
    assert inside.all()
    settings = problem.mpc
    for x, reference, u in zip(x0, references, inputs, strict=True):

        def cost(flat: Array, x=x, reference=reference) -> float:
            states = problem.predict(x, flat.reshape(-1, 3))
            err = states - reference
            weights = np.array([settings.q_pos] * 3 + [settings.q_vel] * 3)
            stage = np.sum(err[:-1] ** 2 * weights) + settings.terminal_factor * np.sum(
                err[-1] ** 2 * weights
            )
            return float(stage + settings.r_acc * np.sum(flat**2))

        flat, step = u.ravel(), 1e-6
        gradient = [(cost(flat + step * e) - cost(flat - step * e)) / (2 * step) for e in np.eye(flat.size)]
        assert np.max(np.abs(gradient)) < 1e-4


def test_a_non_finite_state_fails_alone() -> None:
    problems = [MpcProblem() for _ in range(3)]
    x0 = [np.zeros(6), np.full(6, np.nan), np.zeros(6)]
    references = [hold(x, np.zeros(3)) for x in x0]
    for batched in (True, False):
        answers = BatchSolver(batched).solve(problems, x0, references)
        assert isinstance(answers[1], SolveError)
        assert not isinstance(answers[0], SolveError)
        assert not isinstance(answers[2], SolveError)


def test_one_by_one_is_osqp_for_every_drone() -> None:
    solver = BatchSolver(batched=False)
    solver.solve([MpcProblem(), MpcProblem()], [np.zeros(6)] * 2, [hold(np.zeros(6), np.zeros(3))] * 2)
    assert (solver.counters.exact, solver.counters.iterative, solver.counters.largest) == (0, 2, 2)


def _service(window_s: float, drones: int) -> tuple[Any, Any, list[Any]]:
    """An MPC service on a fake clock with `drones` drones present, and a State publisher for each."""
    from dynqos.common import keys
    from dynqos.common.bus import MemoryBus, Priority
    from dynqos.common.clock import FakeClock
    from dynqos.common.config import Config
    from dynqos.common.keys import Flow, Stream
    from dynqos.edge.mpc.service import MpcService
    from dynqos.edge.runtime import Ports

    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    for i in range(drones):
        bus.declare_token(keys.drone_presence(f"uav{i}"))
    service = MpcService(Config(mpc=MpcConfig(batch_window_s=window_s)), Ports(bus, clock))
    publishers = [
        bus.publisher(keys.uplink(f"uav{i}", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
        for i in range(drones)
    ]
    return service, (bus, clock), publishers


def _state(uav: str, seq: int, clock: Any) -> Any:
    from dynqos.common.messages import State

    return State(uav=uav, seq=seq, stamp_ns=clock.now_ns(), pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                 quat=(1.0, 0.0, 0.0, 0.0))  # fmt: skip


def test_a_fleet_s_states_within_the_window_are_solved_in_one_batch_and_a_drone_alone_at_once() -> None:
    from tests.edge_cores import turn

    service, (bus, clock), publishers = _service(0.002, 3)
    for seq in (1, 2):  # every drone known, each answered (the first round's states come together)
        for i, publisher in enumerate(publishers):
            publisher.put(_state(f"uav{i}", seq, clock))
        bus.pump()
        turn(service, clock.now_ns())
        clock.advance_ns(2_000_000)
        turn(service, clock.now_ns())
    answered, batches = service.counters.commands, service.solver.counters.batches
    assert answered == 6
    publishers[0].put(_state("uav0", 3, clock))  # one drone's State: it waits for the others
    bus.pump()
    assert turn(service, clock.now_ns()) == pytest.approx(0.002)
    assert service.counters.commands == answered
    clock.advance_ns(1_000_000)
    for i in (1, 2):  # the others come within the window
        publishers[i].put(_state(f"uav{i}", 3, clock))
    bus.pump()
    turn(service, clock.now_ns())
    assert service.counters.commands == answered + 3  # all fresh: answered at once, in one batch
    assert service.solver.counters.batches == batches + 1
    publishers[1].put(_state("uav1", 4, clock))  # the others never come: answered once the window ends
    bus.pump()
    assert turn(service, clock.now_ns()) > 0
    assert service.counters.commands == answered + 3
    clock.advance_ns(2_000_000)
    turn(service, clock.now_ns())
    assert service.counters.commands == answered + 4

    alone, (bus, clock), (publisher,) = _service(0.002, 1)
    publisher.put(_state("uav0", 1, clock))
    bus.pump()
    turn(alone, clock.now_ns())
    assert alone.counters.commands == 1  # no wait when alone
    assert alone.gathering_s == 0.0
