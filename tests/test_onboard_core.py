"""The onboard core, tick by tick on a fake clock: who flies, on which flow, and what it reports."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np
import pytest

from dynqos.common.bus import Received
from dynqos.common.config import Config, OnboardConfig, SupervisorConfig, load_config
from dynqos.common.keys import Stream
from dynqos.common.messages import (
    CameraAck,
    Command,
    QosGrant,
    QosMonitoring,
    QosRequest,
    Reference,
    State,
    SupervisorStatus,
    decode,
    encode,
)
from dynqos.common.modes import ControlSource, Flow, Grant, SupervisorState
from dynqos.onboard.core import SETPOINT_PERIOD_NS, STALE_STATE_NS, OnboardCore
from dynqos.onboard.fc import FC_SAID_FRESH_S, AccelSetpoint, FcSaid, FcState, PositionSetpoint
from dynqos.onboard.modem import ModemReading
from dynqos.onboard.tick import FrameSent, TickInput, TickOutput

MS = 1_000_000
QOS_MODES = ["dynamic", "default", "priority"]
EDGE_ACCEL = (0.5, -0.25, 0.0)


def config(qos: str = "dynamic", **onboard: object) -> Config:
    return replace(Config(), onboard=replace(OnboardConfig(), qos=qos, **onboard))  # type: ignore[arg-type]


@dataclass
class Rig:
    """A drone's core, a flight controller that reports where it is, and an edge that answers states.

    The edge answers each State with a Command after `rtt_ms` (when `edge_up`); the FC's state is
    stamped every tick while `fc_up`, and stays at its last stamp when the FC falls silent."""

    core: OnboardCore
    now: int = 1_000 * MS
    rtt_ms: float = 20.0
    edge_up: bool = True
    fc_up: bool = True
    offboard: bool = True
    fc: FcState | None = None
    spaciousness_m: float | None = 8.0
    frame_bytes: int = 0  # > 0: the camera hands the bus an image of this size every tick
    pending: list[tuple[int, Received]] = field(default_factory=list)
    outputs: list[TickOutput] = field(default_factory=list)
    extra: list[Received] = field(default_factory=list)
    modem: ModemReading | None = None  # the modem's reading handed in every tick
    fc_said: FcSaid | None = None  # what the FC said last, handed in every tick

    @classmethod
    def make(cls, qos: str = "dynamic", **kwargs: object) -> Rig:
        return cls(OnboardCore(config(qos), start_ns=1_000 * MS), **kwargs)  # type: ignore[arg-type]

    def tick(self) -> TickOutput:
        self.now += SETPOINT_PERIOD_NS
        if self.fc_up or self.fc is None:
            self.fc = FcState(self.now, (1.0, 2.0, -1.5), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        due = [r for t, r in self.pending if t <= self.now]
        self.pending = [(t, r) for t, r in self.pending if t > self.now]
        downlink, self.extra = [*due, *self.extra], []
        frames = [FrameSent(len(self.outputs), "rgb", self.now, self.frame_bytes)] if self.frame_bytes else []
        out = self.core.tick(
            TickInput(now_ns=self.now, fc=self.fc, downlink=downlink, offboard=self.offboard,
                      spaciousness_m=self.spaciousness_m, frames_sent=frames, modem=self.modem,
                      fc_said=self.fc_said)
        )  # fmt: skip
        for item in out.publish:
            # Everything the core publishes must survive the codec: a status it cannot encode is a crash.
            assert decode(encode(item.message)) == item.message
            if isinstance(item.message, State) and self.edge_up:
                arrival = self.now + round(self.rtt_ms * MS)
                self.pending.append((arrival, Received("cmd", self.command_for(item.message), arrival)))
        self.outputs.append(out)
        return out

    def command_for(self, state: State, uav: str = "uav1") -> Command:
        return Command(uav=uav, seq=state.seq, state_seq=state.seq, state_stamp_ns=state.stamp_ns,
                       edge_hold_ns=0, dt_s=0.05, accel_mps2=[EDGE_ACCEL] * 10,
                       yaw_rad=[0.7] * 10)  # fmt: skip

    def run(self, seconds: float) -> list[TickOutput]:
        return [self.tick() for _ in range(round(seconds * 1e9 / SETPOINT_PERIOD_NS))]

    def run_until(self, source: ControlSource, seconds: float) -> None:
        for _ in range(round(seconds * 1e9 / SETPOINT_PERIOD_NS)):
            self.tick()
            if self.core.control is source:
                return
        raise AssertionError(f"never reached {source} in {seconds} s (control {self.core.control})")

    def statuses(self, outs: Iterable[TickOutput] | None = None) -> list[SupervisorStatus]:
        return [
            p.message
            for o in (self.outputs if outs is None else outs)
            for p in o.publish
            if isinstance(p.message, SupervisorStatus)
        ]

    def events(self) -> list[str]:
        return [e.text for o in self.outputs for e in o.events]


def test_before_offboard_nothing_flies_and_the_state_says_standby() -> None:
    rig = Rig.make(offboard=False)
    outs = rig.run(1.0)
    assert all(o.setpoint is None for o in outs)
    states = [p.message for o in outs for p in o.publish if isinstance(p.message, State)]
    assert len(states) == 20  # every T_mpc = 50 ms
    assert {s.mode for s in states} == {"standby"}
    assert {s.control_source for s in rig.statuses()} == {ControlSource.NONE}
    rig.offboard = True
    rig.run(0.2)
    assert rig.core.offloading
    assert rig.outputs[-1].setpoint is not None


def test_on_the_ground_the_supervisor_observes_and_judges_the_flight_from_offload() -> None:
    """No command reaches a drone before its edge follows it; that is no missed command. The edge's first
    answers are slow (its start-up) and the depth camera sees the ground: none of it is the flight's. Seen
    in CI: a flight that moved to qA or q2 on the ground was still on the priority flow when the load came,
    and a take-off shorter than qA's recovery offloaded into the fallback PID."""
    rig = Rig.make(offboard=False, edge_up=False, spaciousness_m=0.3)
    rig.run(1.0)  # on the ground, no command at all
    rig.edge_up, rig.rtt_ms = True, 300.0
    rig.run(3.0)  # slow answers
    ground = rig.statuses()
    on_the_ground = {(s.state, s.flow, s.camera_rate_factor) for s in ground}
    assert on_the_ground == {(SupervisorState.Q1, Flow.DEFAULT, 1.0)}
    assert (ground[-1].latency, ground[-1].risk) == ("HL", "HR")  # read, not acted on
    assert not any("supervisor:" in e for e in rig.events())
    rig.rtt_ms, rig.spaciousness_m = 20.0, 8.0
    rig.run(0.5)
    rig.offboard = True
    rig.run_until(ControlSource.EDGE, 0.2)
    rig.run(2.0)
    assert not any("fallback PID" in e for e in rig.events())
    assert {s.state for s in rig.statuses()[len(ground) :]} == {SupervisorState.Q1}
    rig.edge_up = False  # once offloading, the watchdog acts as before
    rig.run_until(ControlSource.FALLBACK, 0.5)
    rig.run(0.2)
    assert rig.statuses()[-1].state is SupervisorState.QA


@pytest.mark.parametrize("qos", QOS_MODES)
def test_the_edge_flies_while_commands_come_and_the_watchdog_hands_over_in_time(qos: str) -> None:
    rig = Rig.make(qos)
    rig.run_until(ControlSource.EDGE, 4.0)
    out = rig.tick()
    assert out.setpoint == AccelSetpoint(EDGE_ACCEL, 0.7)  # the edge's setpoint and yaw, untouched
    edge_accel = np.array(EDGE_ACCEL)
    rig.edge_up = False
    before = rig.now
    rig.run_until(ControlSource.FALLBACK, 1.0)
    handed_over_ms = (rig.now - before) / MS
    # The last command answered a state at most T_mpc before; T_wd = 150 ms; plus one 20 ms tick.
    assert handed_over_ms <= 150 + 50 + 20
    first = rig.outputs[-1].setpoint
    assert isinstance(first, AccelSetpoint)
    assert np.allclose(first.accel_mps2, edge_accel, atol=0.2)  # bumpless: the PID starts from the edge's
    status = rig.statuses([rig.outputs[-1]])  # published at the change, not at the next 5 Hz status
    assert len(status) == 1
    assert status[0].control_source is ControlSource.FALLBACK
    assert status[0].fallbacks == rig.core.counters.switches_to_fallback
    age_ms = status[0].command_age_ms
    assert age_ms is not None
    assert 150 < age_ms <= 150 + 20
    assert status[0].control_changed_ns == rig.now
    assert any("fallback PID holding position (watchdog: last valid command" in e for e in rig.events())
    rig.edge_up = True
    rig.run_until(ControlSource.EDGE, 5.0)
    assert rig.statuses()[-1].control_source is ControlSource.EDGE


@pytest.mark.parametrize("qos", QOS_MODES)
def test_fc_silence_holds_position_keeps_the_stream_and_resumes(qos: str) -> None:
    """The crash of an early version: with a fixed flow, FC silence made a status the decoder refused."""
    rig = Rig.make(qos)
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.run(1.0)
    rig.fc_up = False
    silent = rig.run(2.0)
    assert all(o.setpoint is not None for o in silent)  # a setpoint every tick: offboard survives
    held = [o.setpoint for o in silent if isinstance(o.setpoint, PositionSetpoint)]
    assert held
    assert {h.pos_m for h in held} == {(1.0, 2.0, -1.5)}  # where the FC was last seen
    hold_after_ms = (len(silent) - len(held)) * SETPOINT_PERIOD_NS / MS
    assert STALE_STATE_NS / MS - 20 <= hold_after_ms <= STALE_STATE_NS / MS + 20
    states = [p for o in silent[len(silent) - len(held) :] for p in o.publish if p.stream is Stream.STATE]
    assert not states  # a stale state is not published
    assert rig.core.control is ControlSource.HOLD
    assert ControlSource.HOLD in {s.control_source for s in rig.statuses(silent)}
    rig.fc_up = True
    rig.run_until(ControlSource.EDGE, 5.0)
    assert "onboard: the flight controller's state is back" in rig.events()
    assert rig.core.max_setpoint_gap_ms == pytest.approx(20.0)


def test_forged_stale_and_foreign_commands_never_fly() -> None:
    rig = Rig.make("priority", edge_up=False)
    rig.run(0.5)
    assert rig.core.control is ControlSource.FALLBACK
    state = [p.message for o in rig.outputs for p in o.publish if isinstance(p.message, State)][-1]
    assert isinstance(state, State)
    forged = replace(rig.command_for(state), state_stamp_ns=state.stamp_ns + 1)  # an altered echo
    unknown = replace(rig.command_for(state), state_seq=10**6)  # answers no state we sent
    foreign = rig.command_for(state, uav="uav2")
    for command in (forged, unknown, foreign):
        rig.extra.append(Received("cmd", command, rig.now))
        rig.tick()
    assert rig.core.control is ControlSource.FALLBACK
    c = rig.core.tracker.counters
    assert (c.unknown_state, c.wrong_drone, c.accepted) == (2, 1, 0)
    good = rig.command_for(state)
    rig.extra.append(Received("cmd", good, rig.now))
    rig.tick()  # its horizon (500 ms) still covers now: the edge takes over
    assert rig.core.control is ControlSource.EDGE
    rig.extra.append(Received("cmd", good, rig.now))  # a replay
    rig.tick()
    assert rig.core.tracker.counters.duplicates == 1  # a replay is a duplicate: dropped, never applied twice


def _loaded_rig(qos: str, spaciousness_m: float) -> Rig:
    rig = Rig.make(qos, spaciousness_m=spaciousness_m)
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.run(3.0)
    rig.rtt_ms = 120.0  # a loaded default flow
    return rig


def test_dynamic_qos_moves_the_state_to_the_priority_flow_and_back() -> None:
    rig = _loaded_rig("dynamic", spaciousness_m=4.0)  # medium risk: q3 on high latency
    outs = rig.run(3.0)
    assert rig.core.decision is not None
    assert rig.core.decision.state is SupervisorState.Q3
    late = [p for o in outs[-20:] for p in o.publish]
    assert {p.flow for p in late} == {Flow.PRIORITY}  # state and status
    assert outs[-1].camera_flow is Flow.PRIORITY
    rig.rtt_ms = 20.0
    outs = rig.run(10.0)
    probing = [
        o for o in outs if o.camera_flow is Flow.DEFAULT and any(p.flow is Flow.PRIORITY for p in o.publish)
    ]
    assert probing  # the camera probed the default flow while the state stayed on the priority flow
    assert rig.core.decision.state is SupervisorState.Q1
    assert {p.flow for p in outs[-1].publish} <= {Flow.DEFAULT}


def test_rate_adaptation_reaches_the_camera_and_persistent_latency_the_fallback() -> None:
    rig = _loaded_rig("dynamic", spaciousness_m=8.0)  # low risk: q4, rate adaptation on the default flow
    in_q4 = []
    for _ in range(500):
        out = rig.tick()
        assert rig.core.decision is not None
        if rig.core.decision.state is SupervisorState.Q4:
            in_q4.append(out)
        if rig.core.control is ControlSource.FALLBACK:
            break
    assert in_q4
    assert {o.camera_flow for o in in_q4} == {Flow.DEFAULT}
    assert min(o.camera_rate_factor for o in in_q4) < 1.0  # halved, and halved again
    assert {p.flow for o in in_q4 for p in o.publish} == {Flow.DEFAULT}
    # HL still holds at the minimum rate: qA, and the fallback flies although commands still come.
    assert rig.core.decision is not None
    assert rig.core.decision.state is SupervisorState.QA
    assert rig.core.control is ControlSource.FALLBACK
    assert any("fallback PID holding position (supervisor state qA)" in e for e in rig.events())


@pytest.mark.parametrize("qos", ["default", "priority"])
def test_a_fixed_flow_ignores_the_supervisors_flow_and_rate(qos: str) -> None:
    rig = _loaded_rig(qos, spaciousness_m=4.0)
    outs = rig.run(5.0)
    assert rig.core.decision is not None
    assert rig.core.decision.state is not SupervisorState.Q1  # it would switch...
    assert {p.flow for o in outs for p in o.publish} == {Flow(qos)}  # ...but the drone does not
    assert {(o.camera_flow, o.camera_rate_factor) for o in outs} == {(Flow(qos), 1.0)}
    assert {s.flow for s in rig.statuses(outs)} == {Flow(qos)}
    assert rig.core.control is ControlSource.EDGE  # and the edge keeps flying while commands come


@pytest.mark.parametrize("qos", ["dynamic", "default", "priority"])
def test_a_camera_pinned_to_the_default_flow_stays_there_while_the_state_moves(qos: str) -> None:
    """`[supervisor] camera_flow = "default"`: in every QoS mode the state takes the flow it takes
    without the pin (the priority flow on high latency in dynamic QoS, the fixed flow otherwise) and
    the camera never leaves the default flow, the fallback and the probe included."""
    pinned = replace(config(qos), supervisor=replace(SupervisorConfig(), camera_flow="default"))
    rig = Rig(OnboardCore(pinned, start_ns=1_000 * MS), spaciousness_m=4.0)
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.run(3.0)
    rig.rtt_ms = 120.0  # a loaded default flow: q3 in dynamic QoS
    outs = rig.run(3.0)
    rig.edge_up = False  # the fallback (qA), then back
    outs += rig.run(2.0)
    rig.edge_up, rig.rtt_ms = True, 20.0
    outs += rig.run(12.0)
    state_flows = {p.flow for o in outs for p in o.publish}
    assert state_flows == ({Flow.DEFAULT, Flow.PRIORITY} if qos == "dynamic" else {Flow(qos)})
    assert {o.camera_flow for o in outs} == {Flow.DEFAULT}
    assert {s.camera_flow for s in rig.statuses(outs)} == {Flow.DEFAULT}
    if qos == "dynamic":
        states = {s.state for s in rig.statuses(outs)}
        assert {SupervisorState.Q3, SupervisorState.QA, SupervisorState.Q1} <= states


def test_camera_acks_become_latency_samples_in_the_status() -> None:
    rig = Rig.make("dynamic")
    rig.run(0.5)
    stamp = rig.now
    out = rig.core.tick(
        TickInput(now_ns=rig.now + 1, fc=rig.fc, frames_sent=[FrameSent(1, "rgb", stamp, 1000)])
    )
    assert out.setpoint is not None
    ack = CameraAck(uav="uav1", seq=1, frame_seq=1, kind="rgb", stamp_ns=stamp, edge_hold_ns=2 * MS)
    rig.extra.append(Received("ack", ack, stamp + 30 * MS))
    rig.run(0.5)
    samples = [v for s in rig.statuses() for v in s.camera_latency_samples_ms]
    assert samples == [pytest.approx(28.0)]
    assert rig.core.counters.camera_bytes == 1000


def test_the_status_carries_the_shells_running_count_of_uplink_bytes() -> None:
    rig = Rig.make("dynamic")
    rig.run(0.3)
    assert {s.uplink_bytes for s in rig.statuses()} == {0}  # the shell has not said yet
    for count in (5000, 7000, 6000):  # a count read a tick late never moves the total back
        rig.core.tick(TickInput(now_ns=rig.now + 1, fc=rig.fc, uplink_bytes=count))
    rig.run(0.5)
    assert rig.statuses()[-1].uplink_bytes == 7000


def test_fallback_holds_or_continues_the_mission_from_the_last_reference() -> None:
    positions = [(float(k), 0.0, -1.5) for k in range(5)]
    reference = Reference(uav="uav1", seq=1, stamp_ns=0, dt_s=0.05, pos_m=positions,
                          vel_mps=[(20.0, 0.0, 0.0)] * 5, yaw_rad=[0.3] * 5)  # fmt: skip
    hold = OnboardCore(load_config(None, []), start_ns=0)
    hold._hold.pos_m = np.array([9.0, 9.0, -1.0])
    hold.reference.update(reference, 1_000 * MS)
    target, velocity, _ = hold._fallback_target(1_100 * MS)
    assert list(target) == [9.0, 9.0, -1.0]
    assert velocity is None
    cont = OnboardCore(load_config(None, ["onboard.fallback='continue'"]), start_ns=0)
    cont._hold.pos_m = np.array([9.0, 9.0, -1.0])
    assert list(cont._fallback_target(1_100 * MS)[0]) == [9.0, 9.0, -1.0]  # no reference yet: hold
    cont.reference.update(reference, 1_000 * MS)
    target, velocity, yaw = cont._fallback_target(1_100 * MS)  # 100 ms after arrival: sample 2
    assert list(target) == pytest.approx([2.0, 0.0, -1.5])
    assert velocity is not None
    assert velocity[0] == pytest.approx(20.0)
    assert yaw == pytest.approx(0.3)
    target, velocity, _ = cont._fallback_target(5_000 * MS)  # long after: the last sample, no velocity
    assert list(target) == pytest.approx([4.0, 0.0, -1.5])
    assert velocity is not None
    assert velocity[0] == 0.0


def test_log_events_carry_levels() -> None:
    rig = Rig.make("priority")
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.fc_up = False
    rig.run(1.0)
    levels = {e.text: e.level for o in rig.outputs for e in o.events}
    assert any(t.startswith("onboard: no state from the flight controller") for t in levels)
    assert logging.ERROR in levels.values()


# ---- the request for priority and the network's grant (docs/qos.md) --------------------------------------


def requests(outs: Iterable[TickOutput]) -> list[tuple[Flow, bool]]:
    return [(p.flow, p.message.want) for o in outs for p in o.publish if isinstance(p.message, QosRequest)]


class Agent:
    """A QoS agent answering every request, as `dynqos edge qos` does, with a grant of its choosing."""

    def __init__(self, rig: Rig, grant: Grant | None) -> None:
        self.rig, self.grant, self.seq = rig, grant, 0

    def answer(self, outs: Iterable[TickOutput]) -> None:
        if self.grant is None:
            return  # no agent at the edge
        for want in [w for _, w in requests(outs)]:
            self.seq += 1
            grant = self.grant if want else Grant.NONE
            message = QosGrant(uav="uav1", seq=self.seq, grant=grant, backend="camara", reason="test")
            self.rig.extra.append(Received("qos", message, self.rig.now))

    def run(self, seconds: float) -> list[TickOutput]:
        outs = []
        for _ in range(round(seconds * 1e9 / SETPOINT_PERIOD_NS)):
            out = self.rig.tick()
            self.answer([out])
            outs.append(out)
        return outs


@pytest.mark.parametrize("qos", QOS_MODES)
def test_the_drone_asks_for_priority_exactly_while_its_flow_is_the_priority_flow(qos: str) -> None:
    rig = Rig.make(qos, offboard=False, spaciousness_m=4.0)
    assert requests(rig.run(1.0)) == []  # on the ground nobody asks
    rig.offboard = True
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.run(3.0)
    rig.rtt_ms = 120.0  # loaded: dynamic moves to q3, the priority flow
    outs = rig.run(4.0)
    asked = requests(rig.outputs)
    if qos == "default":
        assert asked == []  # never asks
        return
    if qos == "dynamic":  # it offloads in q1 (the watchdog on the ground is no missed command)
        assert asked[0] == (Flow.DEFAULT, False)
    # it goes on the flow chosen in that tick, and wants priority exactly when that is the priority flow
    assert all(want is (qos == "priority" or flow is Flow.PRIORITY) for flow, want in asked)
    assert (Flow.PRIORITY, True) in requests(outs)
    if qos == "dynamic":
        assert (Flow.DEFAULT, False) in requests(rig.outputs)
        changes = [i for i, o in enumerate(outs) if any(p.flow is Flow.PRIORITY for p in o.publish)]
        assert requests([outs[changes[0]]]) == [(Flow.PRIORITY, True)]  # asked in the tick it moved
    assert 3 <= len(requests(outs)) <= 6  # then repeated every request_interval_s (1 s), not every tick


@pytest.mark.parametrize("qos", ["dynamic", "priority"])
def test_the_status_reports_the_grant_and_says_when_no_agent_answers(qos: str) -> None:
    rig = _loaded_rig(qos, spaciousness_m=4.0)
    agent = Agent(rig, Grant.AVAILABLE)
    agent.run(3.0)
    last = rig.statuses()[-1]
    assert (last.qos_grant, last.qos_agent) == (Grant.AVAILABLE, True)
    assert any("grant is available" in e for e in rig.events())
    agent.grant = None  # the agent is gone: the drone flies on, links only, and says so
    rig.run(4.0)
    last = rig.statuses()[-1]
    assert (last.qos_grant, last.qos_agent) == (Grant.NONE, False)
    assert rig.core.control is ControlSource.EDGE


def test_a_refused_grant_sends_the_drone_to_rate_adaptation_at_once() -> None:
    rig = _loaded_rig("dynamic", spaciousness_m=4.0)
    agent = Agent(rig, Grant.UNAVAILABLE)
    for _ in range(100):
        agent.run(0.05)
        assert rig.core.decision is not None
        if rig.core.decision.state is SupervisorState.Q6:
            break
    assert rig.core.decision is not None
    assert rig.core.decision.state is SupervisorState.Q6
    assert "the network refused" in rig.core.supervisor.log[-1].cause
    assert rig.statuses()[-1].qos_grant is Grant.UNAVAILABLE
    assert any("grant is unavailable (test)" in e for e in rig.events())


def test_priority_stays_wanted_into_the_fallback_it_led_to_and_is_released_after() -> None:
    rig = _loaded_rig("dynamic", spaciousness_m=4.0)  # q3, then q6, then qA at the lowest camera rate
    for _ in range(1000):
        rig.tick()
        if rig.core.control is ControlSource.FALLBACK:
            break
    assert rig.core.decision is not None
    assert rig.core.decision.state is SupervisorState.QA
    outs = rig.run(2.0)
    assert set(requests(outs)) == {(Flow.PRIORITY, True)}  # q6 -> qA: still wanted
    rig.rtt_ms = 20.0
    rig.run_until(ControlSource.EDGE, 20.0)
    rig.run(2.0)
    assert requests(rig.outputs)[-1] == (Flow.DEFAULT, False)


def test_the_request_carries_the_drones_need_and_a_new_risk_is_said_at_once() -> None:
    rig = _loaded_rig("dynamic", spaciousness_m=4.0)  # MR (3..5 m), latency high: q3, priority wanted
    rig.frame_bytes = 12_500  # 50 images a second: 5 Mbit/s
    rig.run(3.0)
    asked = [p.message for o in rig.outputs for p in o.publish if isinstance(p.message, QosRequest)]
    wanted = [r for r in asked if r.want]
    assert wanted
    assert wanted[-1].risk == "MR"
    assert wanted[-1].latency_excess > 0  # P_lat over th_lat: the supervisor sees high latency
    assert wanted[-1].offered_mbps == pytest.approx(5.0, rel=0.05)
    rig.spaciousness_m = 1.0  # clutter closer than 3 m: high risk
    before = len(rig.outputs)
    for _ in range(50):  # within a second (the repeat period), well before it
        rig.tick()
        new = [
            p.message for o in rig.outputs[before:] for p in o.publish if isinstance(p.message, QosRequest)
        ]
        if any(r.risk == "HR" for r in new):
            break
    assert any(r.risk == "HR" and r.want for r in new)
    assert len(rig.outputs) - before < 50


def test_a_status_carries_the_modems_reading_while_it_is_fresh() -> None:
    rig = Rig.make()
    before = rig.statuses(rig.run(0.5))
    assert before
    assert all(s.rsrp_dbm is None and s.sinr_db is None for s in before)
    rig.modem = ModemReading(-85.5, 12.0, rig.now)
    fresh = rig.statuses(rig.run(0.5))
    assert fresh
    assert {(s.rsrp_dbm, s.sinr_db) for s in fresh} == {(-85.5, 12.0)}
    rig.modem = None  # no new reading: the last one holds for three modem intervals (3 s), then goes
    rig.run(2.0)
    assert rig.statuses(rig.run(0.2))[-1].rsrp_dbm == -85.5
    assert rig.statuses(rig.run(1.0))[-1].rsrp_dbm is None


def test_a_status_carries_what_the_flight_controller_said_while_it_is_recent() -> None:
    rig = Rig.make()
    assert {(s.fc_text, s.fc_severity) for s in rig.statuses(rig.run(0.5))} == {("", None)}
    rig.fc_said = FcSaid("Preflight Fail: Accel uncalibrated", 2, rig.now)
    said = rig.statuses(rig.run(0.5))
    assert said
    assert {(s.fc_text, s.fc_severity) for s in said} == {("Preflight Fail: Accel uncalibrated", 2)}
    rig.fc_said = None  # it said nothing since: the words ride along for FC_SAID_FRESH_S, then go
    rig.run(FC_SAID_FRESH_S - 1.0)
    assert rig.statuses(rig.run(0.2))[-1].fc_text == "Preflight Fail: Accel uncalibrated"
    assert (rig.statuses(rig.run(1.0))[-1].fc_text, rig.statuses()[-1].fc_severity) == ("", None)
    rig.fc_said = FcSaid("Takeoff detected", 6, rig.now)  # newer words replace them
    assert rig.statuses(rig.run(0.5))[-1].fc_text == "Takeoff detected"


def test_a_radio_aware_supervisor_hears_the_modems_sinr_while_it_is_fresh() -> None:
    cfg = config()
    rig = Rig(
        OnboardCore(replace(cfg, supervisor=replace(cfg.supervisor, radio_aware=True)), start_ns=1_000 * MS)
    )
    rig.run(1.0)
    rig.modem = ModemReading(-110.0, -10.0, rig.now)  # a fading link, the RTT still 20 ms
    faded = rig.statuses(rig.run(0.5))
    assert faded[-1].latency == "HL"
    assert faded[-1].sinr_db == -10.0
    rig.modem = None
    rig.run(3.5)  # the reading is stale: only the samples speak again
    assert rig.statuses(rig.run(0.5))[-1].latency == "LL"


def test_the_cores_delay_reports_reach_the_supervisor_while_fresh_and_only_the_drones_own() -> None:
    """A QosMonitoring forwarded by the agent ([supervisor] network_aware): its round trip is an input
    for two of its reporting periods after it arrived; another drone's report is not."""
    cfg = config("dynamic")
    aware = replace(cfg, supervisor=replace(cfg.supervisor, network_aware=True))
    rig = Rig(OnboardCore(aware, start_ns=1_000 * MS), spaciousness_m=4.0)
    rig.run_until(ControlSource.EDGE, 4.0)
    rig.run(3.0)

    def report(uav: str, seq: int) -> Received:
        message = QosMonitoring(
            uav=uav, seq=seq, stamp_ns=0, subscription_id="s1", round_trip_ms=90.0, period_s=1
        )
        return Received("qos", message, rig.now)

    rig.extra.append(report("uav2", 1))
    rig.run(1.0)
    assert rig.core.network.reports == 0
    assert rig.core.decision is not None
    assert rig.core.decision.state is SupervisorState.Q1  # its own RTT is low: nothing to act on
    rig.extra.append(report("uav1", 2))
    rig.run(0.5)
    assert rig.core.network.reports == 1
    assert rig.core.decision.state is SupervisorState.Q3  # the report alone reads HL (MR: priority)
    assert rig.core.network.round_trip_ms(rig.now) == 90.0
    rig.run(1.6)  # two periods after it arrived, no newer one: stale
    assert rig.core.network.round_trip_ms(rig.now) is None
