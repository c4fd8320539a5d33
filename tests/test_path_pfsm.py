"""The supervisor across two paths (docs/supervisor.md, "Two paths"), tick by tick on a fake clock: each
path's own PFSM sets its flow and asks its own site's agent for priority, from its own windows; the
drone's PFSM, on the Commands applied, keeps the drone on the edge while either path answers in time."""

from __future__ import annotations

import pytest

from dynqos.common.bus import Received
from dynqos.common.config import Config, SupervisorConfig
from dynqos.common.messages import Command, QosGrant, QosRequest, State
from dynqos.common.modes import ControlSource, Flow, Grant, SupervisorState
from dynqos.onboard.answers import Answers
from dynqos.onboard.core import OnboardCore
from dynqos.onboard.path_pfsm import PathSupervisors
from dynqos.onboard.tick import Outgoing, TickOutput
from tests.test_multipath_core import MS, TwoPaths, two_paths

MEDIUM_RISK_M = 4.0  # spaciousness read as MR: a loaded path asks for priority rather than throttling
START_NS = 1_000 * MS


def rig(qos: str = "dynamic", space_m: float = MEDIUM_RISK_M) -> TwoPaths:
    return TwoPaths(OnboardCore(two_paths(qos), start_ns=START_NS), space_m=space_m)


def _items(outs: list[TickOutput], kind: type) -> list[Outgoing]:
    return [p for o in outs for p in o.publish if isinstance(p.message, kind)]


def _last_want(outs: list[TickOutput], path: str) -> bool | None:
    wants = [p.message.want for p in _items(outs, QosRequest) if p.path == path]
    return wants[-1] if wants else None


def test_a_loaded_path_takes_the_priority_flow_and_asks_its_site_while_the_other_stays_default() -> None:
    r = rig()
    r.run(3.0)
    r.rtt_ms["b"] = 60.0  # cell B loaded: path b answers late, path a still first and in time
    outs = r.run(2.0)
    pfsms = r.core.path_pfsms
    assert pfsms is not None
    assert pfsms.decisions["b"].state is SupervisorState.Q3  # MR and HL on its own window
    assert pfsms.decisions["a"].state is SupervisorState.Q1
    assert r.core.decision is not None
    assert r.core.decision.state is SupervisorState.Q1
    assert r.core.control is ControlSource.EDGE
    sent = _items(outs, State)[-1]
    assert (sent.flow_on("a"), sent.flow_on("b")) == (Flow.DEFAULT, Flow.PRIORITY)
    assert _last_want(outs, "b") is True
    assert _last_want(outs, "a") in (None, False)  # path a never asked its operator for priority
    assert all(p.path in ("a", "b") for p in _items(outs, QosRequest))  # each request on its own path
    status = r.statuses(outs)[-1]
    assert dict((p, (s, f)) for p, s, f in status.path_states) == {
        "a": (SupervisorState.Q1, Flow.DEFAULT),
        "b": (SupervisorState.Q3, Flow.PRIORITY),
    }
    assert status.flow is Flow.PRIORITY  # the drone's traffic is on the priority flow somewhere
    assert "pfsm_b" in r.core.health()
    assert r.core.health()["pfsm_b"] == "q3/priority"
    # cell B's load ends: path b goes back to the default flow (after recovery and its probe) and
    # withdraws its request
    r.rtt_ms["b"] = 18.0
    outs = r.run(8.0)  # recover_s, doubled after the start-up's recovery (anti-flap), and probe_s
    assert pfsms.decisions["b"].state is SupervisorState.Q1
    assert _items(outs, State)[-1].flow_on("b") is Flow.DEFAULT
    assert _last_want(outs, "b") is False


def test_a_silent_path_goes_to_qa_alone_and_the_drone_flies_on_the_other() -> None:
    r = rig()
    r.run(3.0)
    r.rtt_ms["b"] = None  # cell B out
    outs = r.run(1.0)
    pfsms = r.core.path_pfsms
    assert pfsms is not None
    assert pfsms.decisions["b"].state is SupervisorState.QA  # its own watchdog
    assert pfsms.decisions["a"].state is SupervisorState.Q1
    assert r.core.control is ControlSource.EDGE  # the drone's watchdog is on the Commands it applies
    assert _last_want(outs, "b") in (None, False)  # qA after a watchdog in q1 asks for nothing
    r.rtt_ms["b"] = 18.0
    r.run(3.0)
    assert pfsms.decisions["b"].state is SupervisorState.Q1  # fresh evidence, LL for recover_s


def test_a_refusal_by_one_site_is_that_path_s_alone() -> None:
    r = rig()
    r.run(3.0)
    r.rtt_ms["b"] = 60.0
    r.run(1.0)
    pfsms = r.core.path_pfsms
    assert pfsms is not None
    assert pfsms.decisions["b"].state is SupervisorState.Q3
    for site, grant in (("a", Grant.AVAILABLE), ("b", Grant.UNAVAILABLE)):
        message = QosGrant(uav="uav1", seq=1, grant=grant, backend="camara", site=site, reason="test")
        r.pending.append((r.now, Received("grant", message, r.now, site)))
    r.run(0.5)
    assert pfsms.decisions["b"].signals.priority_denied
    assert not pfsms.decisions["a"].signals.priority_denied
    # waiting for a priority its operator refused is waiting for nothing: path b escalates at once
    assert pfsms.decisions["b"].state is SupervisorState.Q6


@pytest.mark.parametrize("qos", ["default", "priority"])
def test_a_fixed_flow_is_the_same_on_both_paths_and_asked_on_both_or_neither(qos: str) -> None:
    r = rig(qos)
    r.run(3.0)
    r.rtt_ms["b"] = 60.0
    outs = r.run(3.0)
    flow = Flow(qos)
    sent = _items(outs, State)[-1]
    assert (sent.flow_on("a"), sent.flow_on("b")) == (flow, flow)
    expected = True if qos == "priority" else None
    assert (_last_want(outs, "a"), _last_want(outs, "b")) == (expected, expected)


def test_both_paths_loaded_is_the_drone_s_priority_too() -> None:
    r = rig()
    r.run(3.0)
    r.rtt_ms.update(a=60.0, b=70.0)
    outs = r.run(3.0)
    pfsms = r.core.path_pfsms
    assert pfsms is not None
    assert {d.state for d in pfsms.decisions.values()} == {SupervisorState.Q3}
    assert r.core.decision is not None
    assert r.core.decision.state is SupervisorState.Q3
    assert (_last_want(outs, "a"), _last_want(outs, "b")) == (True, True)


def test_one_path_has_no_path_pfsm_and_asks_on_its_only_path() -> None:
    core = OnboardCore(Config(), start_ns=0)
    assert core.path_pfsms is None
    assert tuple(core.asking.asked) == ("",)


def test_before_its_first_step_a_path_is_on_the_default_flow_and_wants_nothing() -> None:
    pfsms = PathSupervisors(SupervisorConfig(), {"a": "a", "b": "b"}, 150 * MS, START_NS)
    assert pfsms.flows() == (("a", Flow.DEFAULT), ("b", Flow.DEFAULT))
    assert pfsms.camera_flow("a") is Flow.DEFAULT
    assert [(n.path, n.flow, n.state, n.risk) for n in pfsms.needs()] == [
        ("a", Flow.DEFAULT, None, "NA"),
        ("b", Flow.DEFAULT, None, "NA"),
    ]
    assert pfsms.health() == {}


def test_an_answer_times_the_path_its_state_copy_went_by_whichever_path_it_came_down() -> None:
    """Each site answers each path's copy of a State (edge/mpc/service.py): path b's uplink is slow, so
    its copy's answers are late, though they come down path a; path a's copy is answered at once."""
    answers = Answers("uav1", 150 * MS, 50, ("a", "b"), START_NS)
    paths = answers.paths
    assert paths is not None
    for seq in range(1, 4):
        stamp = START_NS + seq * 50 * MS
        answers.tracker.state_sent(seq, stamp)
        for site, copy_path, rtt_ms in (("a", "a", 12), ("b", "a", 14), ("a", "b", 70), ("b", "b", 72)):
            command = Command(uav="uav1", seq=seq, state_seq=seq, state_stamp_ns=stamp, edge_hold_ns=0,
                              dt_s=0.05, accel_mps2=[(0.1, 0.0, 0.0)] * 10, yaw_rad=[0.0] * 10, term=1,
                              replica=f"mpc-{site}", site=site, state_path=copy_path)  # fmt: skip
            answers.offer(command, stamp + rtt_ms * MS, "a")  # all down path a
    assert list(paths.records["a"].rtts.last(3)) == [12.0, 12.0, 12.0]  # the first answer to a's copy
    assert list(paths.records["b"].rtts.last(3)) == [70.0, 70.0, 70.0]  # b's uplink, timed
    assert paths.records["b"].answered_seq == 3
