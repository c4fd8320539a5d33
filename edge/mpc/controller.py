"""One MPC controller per drone: reference handling, delay compensation, command horizons. Pure.

Timing (docs/architecture.md, "Time"): a Command carries the state's own stamp; setpoint k applies at
state_stamp + k * dt on the drone's clock, so no clock sync is needed and a late command is still
usable. With delay compensation, the initial state is predicted forward by the drone's RTT estimate
using the inputs the drone will be applying meanwhile (from the commands already sent), and the
optimal sequence starts at that predicted instant; the first slots of the horizon carry those
already-committed inputs.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.config import ControlConfig, MpcConfig
from dynqos.common.geometry import yaw_of
from dynqos.common.message_base import MAX_HORIZON
from dynqos.common.messages import STANDING_BY, State
from dynqos.common.reference import ReferenceTrack
from dynqos.edge.mpc.problem import Array, MpcProblem

HISTORY = 64


@dataclass(frozen=True, slots=True)
class Plan:
    """What to send for one state: the Command's horizon, before edge_hold is known."""

    state_seq: int
    state_stamp_ns: int
    dt_s: float
    accel_mps2: tuple[tuple[float, float, float], ...]
    yaw_rad: tuple[float, ...]
    committed_steps: int


@dataclass(frozen=True, slots=True)
class Pending:
    """A state made ready to solve: the QP's initial state and reference, and what the plan needs after."""

    state: State
    x_start: Array
    reference: Array
    yaws: Array
    past: Array
    committed: int
    steps: int


@dataclass(slots=True)
class _SentCommand:
    stamp_ns: int
    accel: Array


class DroneController:
    def __init__(self, uav: str, mpc: MpcConfig | None = None, control: ControlConfig | None = None) -> None:
        self.uav = uav
        self.mpc = mpc or MpcConfig()
        self.problem = MpcProblem(self.mpc, control)
        self.reference = ReferenceTrack()
        self.last_seq: int | None = None
        self.hold: Array | None = None
        self.hold_yaw = 0.0
        self._held: tuple[Array, Array] | None = None  # the hold's reference and yaws, built once
        self._sent: deque[_SentCommand] = deque(maxlen=HISTORY)
        self.last_seen_ns = 0
        self.stale = 0

    def _committed_inputs(self, stamp_ns: int, steps: int, rtt_ns: int) -> Array:
        """The inputs the drone will apply in [stamp, stamp + steps * dt): from the command that has
        arrived there by then (sent for an earlier state, arriving about one RTT after its stamp)."""
        dt_ns = round(self.problem.dt_s * NS_PER_S)
        out = np.zeros((steps, 3))
        for j in range(steps):
            t = stamp_ns + j * dt_ns
            active = None
            for sent in reversed(self._sent):
                if sent.stamp_ns + rtt_ns <= t:
                    active = sent
                    break
            if active is not None:
                k = min((t - active.stamp_ns) // dt_ns, len(active.accel) - 1)
                out[j] = active.accel[k]
        return out

    def step(self, state: State, arrival_ns: int) -> Plan | None:
        """A plan for this state, or None if it is stale (an older or repeated seq). Raises SolveError."""
        pending = self.prepare(state, arrival_ns)
        if pending is None:
            return None
        return self.finish(pending, self.problem.solve(pending.x_start, pending.reference))

    def prepare(self, state: State, arrival_ns: int) -> Pending | None:
        """The QP for this state (solved alone by `step`, or with the fleet's by edge/mpc/batch.py), or
        None if the state is stale."""
        if self.last_seq is not None and state.seq <= self.last_seq:
            self.stale += 1
            return None
        self.last_seq = state.seq
        self.last_seen_ns = arrival_ns
        s = self.mpc
        dt = self.problem.dt_s
        n = self.problem.horizon
        x0 = np.array([*state.pos_m, *state.vel_mps])
        rtt_s = min(state.rtt_est_ms / 1000.0, s.max_compensation_s) if s.compensate_delay else 0.0
        committed = min(round(rtt_s / dt), MAX_HORIZON - 1)
        steps = max(1, min(s.command_steps, MAX_HORIZON - committed, n))
        rtt_ns = to_ns(rtt_s)
        past = self._committed_inputs(state.stamp_ns, committed, rtt_ns)
        x_start = self.problem.predict(x0, past)[-1] if committed else x0
        ref_start_ns = arrival_ns - rtt_ns // 2 + to_ns(committed * dt)
        window = self.reference.window(ref_start_ns, n + 1, dt)
        if window is None:
            # No reference: hold where the last one ended, or where the drone first flew offboard (the
            # planner starts its mission there; standing and climbing, the hold follows the drone).
            if self.hold is None or state.mode == STANDING_BY:
                self.hold = x0[:3].copy()
                self.hold_yaw = yaw_of(state.quat)
                self._held = None
            if self._held is None:  # the same arrays while the hold stays (nothing writes into them)
                reference = np.tile(np.concatenate([self.hold, np.zeros(3)]), (n + 1, 1))
                self._held = (reference, np.full(n + 1, self.hold_yaw))
            reference, yaws = self._held
        else:
            reference, yaws = window
            self.hold = reference[-1, :3].copy()
            self.hold_yaw = float(yaws[-1])
            self._held = None
        return Pending(state, x_start, reference, yaws, past, committed, steps)

    def finish(self, pending: Pending, inputs: Array) -> Plan:
        """The plan from the QP's optimal inputs (N, 3): the committed slots, then the first `steps`."""
        p = pending
        accel = np.vstack([p.past, inputs[: p.steps]]) if p.committed else inputs[: p.steps]
        self._sent.append(_SentCommand(p.state.stamp_ns, accel))
        yaws = p.yaws[: p.steps]
        yaw_seq = np.concatenate([np.full(p.committed, p.yaws[0]), yaws]) if p.committed else yaws
        return Plan(
            state_seq=p.state.seq,
            state_stamp_ns=p.state.stamp_ns,
            dt_s=self.problem.dt_s,
            accel_mps2=tuple(map(tuple, accel.tolist())),  # tolist: Python floats in one C call
            yaw_rad=tuple(yaw_seq.tolist()),
            committed_steps=p.committed,
        )
