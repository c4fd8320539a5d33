"""The QoS agent's per-drone rules (edge/qos/grants.py) on a fake clock: what call is due, what the
drone is told."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from dynqos.common.clock import NS_PER_S
from dynqos.common.config import CamaraConfig, QosConfig
from dynqos.common.modes import Grant
from dynqos.edge.qos.grants import OPS, DroneGrant, Need, Op, QodStatus, Session, SessionState

S = NS_PER_S
CAMARA = QosConfig(
    backend="camara",
    hold_down_s=5.0,
    drone_timeout_s=5.0,
    camara=CamaraConfig(api_root="http://127.0.0.1:1", duration_s=60, extend_before_s=10, poll_interval_s=0.2,
                        retry_after_denied_s=10.0),
)  # fmt: skip


def available(expires_ns: int, sid: str = "s1") -> Session:
    return Session(sid, QodStatus.AVAILABLE, "", expires_ns)


def next_op(g: DroneGrant, now_ns: int) -> Op | None:
    """The next call other than the periodic read of an AVAILABLE session (answered: unchanged)."""
    op = g.next_op(now_ns)
    while op is Op.POLL and g.session is not None and g.session.status is QodStatus.AVAILABLE:
        g.observed(g.session, now_ns)
        op = g.next_op(now_ns)
    return op


def test_links_backend_grants_at_once_and_makes_no_call() -> None:
    g = DroneGrant("uav1", QosConfig(backend="links"), 0)
    assert g.grant(0) is Grant.NONE
    g.request(True, 1, S)
    assert g.next_op(S) is None
    assert g.grant(S) is Grant.AVAILABLE
    g.request(False, 2, 2 * S)
    assert g.grant(2 * S) is Grant.NONE


def test_create_poll_until_available_then_extend_before_expiry() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    assert g.next_op(0) is Op.CREATE
    assert g.grant(0) is Grant.REQUESTED
    g.observed(Session("s1", QodStatus.REQUESTED), 0)
    assert g.next_op(0) is None  # not before the poll interval
    assert g.next_op(int(0.2 * S)) is Op.POLL
    g.observed(available(60 * S), int(0.2 * S))
    assert g.grant(int(0.2 * S)) is Grant.AVAILABLE
    g.request(True, 2, 45 * S)  # the drone keeps asking
    assert g.next_op(45 * S) is Op.POLL  # an AVAILABLE session is read now and then (a network end shows)
    g.observed(available(60 * S), 45 * S)
    assert g.next_op(45 * S) is None
    assert g.next_deadline_ns(45 * S) <= 50 * S  # it wakes for the extension
    g.request(True, 3, 50 * S)
    assert next_op(g, 50 * S) is Op.EXTEND  # 10 s before expiry, still wanted
    g.observed(available(120 * S), 50 * S)
    assert g.next_op(50 * S) is None


def test_release_waits_for_the_hold_down_and_a_flap_does_not_churn() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(600 * S), 0)
    g.request(False, 2, 1 * S)
    assert next_op(g, 1 * S) is None
    assert next_op(g, 5 * S) is None  # 4 s out of priority: held
    g.request(True, 3, 5 * S)  # back in priority: the session was kept
    g.request(False, 4, 6 * S)
    assert next_op(g, 10 * S) is None  # the hold-down counts from the last change
    assert next_op(g, 11 * S) is Op.DELETE
    g.deleted(11 * S)
    assert g.grant(11 * S) is Grant.NONE
    assert next_op(g, 12 * S) is None


def test_a_drone_gone_silent_is_released_after_its_timeout_and_the_hold_down() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(600 * S), 0)
    assert g.wants(5 * S)
    assert not g.wants(6 * S)  # silent for longer than drone_timeout_s
    assert next_op(g, 6 * S) is None  # the hold-down runs from its timeout (5 s)
    assert next_op(g, 9 * S) is None
    assert next_op(g, 10 * S) is Op.DELETE


def test_a_session_the_network_ends_is_deleted_at_once_and_asked_again_after_backoff() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(Session("s1", QodStatus.UNAVAILABLE, "NETWORK_TERMINATED"), S)
    assert g.grant(S) is Grant.UNAVAILABLE
    assert "NETWORK_TERMINATED" in g.reason
    assert g.next_op(S) is Op.DELETE
    g.deleted(S)
    assert g.grant(S) is Grant.UNAVAILABLE  # still refused while wanted
    g.request(True, 2, 5 * S)
    assert g.next_op(5 * S) is None
    g.request(True, 3, 11 * S)
    assert g.next_op(11 * S) is Op.CREATE  # 10 s back-off
    g.observed(Session("s2", QodStatus.UNAVAILABLE, "NETWORK_TERMINATED"), 12 * S)
    g.deleted(12 * S)
    g.request(True, 4, 31 * S)
    assert g.next_op(31 * S) is None  # the back-off doubled: 20 s
    g.request(True, 5, 32 * S)
    assert g.next_op(32 * S) is Op.CREATE


@pytest.mark.parametrize(
    ("op", "expires_s", "again_s"),
    [(Op.CREATE, 0, 10), (Op.POLL, 600, 1), (Op.EXTEND, 5, 1), (Op.DELETE, 600, 1)],
)
def test_a_failed_call_is_tried_again_later_not_at_once(op: Op, expires_s: int, again_s: int) -> None:
    g = DroneGrant("uav1", replace(CAMARA, hold_down_s=0.0), 0)
    g.request(op is not Op.DELETE, 1, 0)
    if op is not Op.CREATE:
        g.observed(available(expires_s * S), 0)
    assert g.next_op(0) is (None if op is Op.POLL else op)
    g.failed(op, "503 UNAVAILABLE: busy", 0)
    assert g.next_op(0) is None
    g.request(op is not Op.DELETE, 2, again_s * S - 1)
    assert g.next_op(again_s * S - 1) is None
    g.request(op is not Op.DELETE, 3, again_s * S)
    assert (g.next_op(again_s * S) if op is Op.POLL else next_op(g, again_s * S)) is op
    if op is Op.CREATE:
        assert g.grant(0) is Grant.UNAVAILABLE
        assert "503" in g.reason


def test_a_new_episode_asks_at_once_even_after_a_refusal() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.denied("422 QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE", 0)
    assert g.grant(0) is Grant.UNAVAILABLE
    g.request(False, 2, S)
    assert g.grant(S) is Grant.NONE
    g.request(True, 3, 2 * S)
    assert g.next_op(2 * S) is Op.CREATE
    assert g.grant(2 * S) is Grant.REQUESTED  # not the last episode's refusal
    g.denied("422 again", 2 * S)
    g.request(True, 4, 3 * S)
    assert g.grant(3 * S) is Grant.UNAVAILABLE  # within an episode a refusal holds until a grant


def test_a_notification_makes_the_session_read_at_once() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(600 * S), 0)
    assert g.next_op(0) is None
    g.read_now()
    assert g.next_op(0) is Op.POLL


def test_a_drone_the_arbiter_does_not_admit_is_told_why_and_its_session_goes_at_once() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.admit(False, "the arbiter: waiting")
    g.request(True, 1, 0)
    assert next_op(g, 0) is None  # no session is asked for before the arbiter admits it
    assert g.grant(0) is Grant.UNAVAILABLE
    assert g.why() == "the arbiter: waiting"
    g.admit(True, "")
    assert next_op(g, 0) is Op.CREATE
    g.observed(available(60 * S), 0)
    assert g.grant(0) is Grant.AVAILABLE
    g.admit(False, "the arbiter: for uav2 (HR)")  # revoked while still wanted: no hold-down
    assert next_op(g, S) is Op.DELETE
    assert g.grant(S) is Grant.UNAVAILABLE
    g.deleted(S)
    assert next_op(g, 2 * S) is None
    assert not g.lingering(2 * S)


def test_a_drone_in_its_hold_down_is_lingering_until_its_session_is_gone() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(60 * S), 0)
    assert not g.lingering(0)
    g.request(False, 2, S)
    assert g.lingering(2 * S)
    assert next_op(g, 6 * S) is Op.DELETE  # the hold-down (5 s) is over
    g.deleted(6 * S)
    assert not g.lingering(6 * S)


class CappingOperator:
    """A spec-legal operator in miniature: every session is capped at `max_s` from its start (the QoS
    profile's maxDuration), an extend past it answers 200 with an unchanged end, a session past its end
    is UNAVAILABLE (DURATION_EXPIRED), and a device holds one session at a time."""

    def __init__(self, max_s: float) -> None:
        self.max_ns = int(max_s * S)
        self.sessions: dict[str, int] = {}  # id -> end
        self.calls = {op: 0 for op in Op}
        self.made = 0

    def answer(self, op: Op, g: DroneGrant, now_ns: int) -> None:
        self.calls[op] += 1
        if op in (Op.DELETE, Op.RENEW):
            assert g.session is not None
            self.sessions.pop(g.session.session_id, None)
            g.deleted(now_ns)
            if op is Op.DELETE:
                return
            self.calls[Op.CREATE] += 1  # the shell goes on to create the successor
        if op in (Op.CREATE, Op.RENEW):
            assert not self.sessions, "a second session for one device: the operator answers 409"
            self.made += 1
            sid = f"s{self.made}"
            self.sessions[sid] = now_ns + self.max_ns
            g.observed(available(self.sessions[sid], sid), now_ns)
            return
        assert g.session is not None
        end = self.sessions[g.session.session_id]
        if op is Op.EXTEND:
            g.extended(available(end, g.session.session_id), now_ns)  # capped: the end does not move
        elif now_ns >= end:
            g.observed(Session(g.session.session_id, QodStatus.UNAVAILABLE, "DURATION_EXPIRED", end), now_ns)
        else:
            g.observed(available(end, g.session.session_id), now_ns)


@pytest.mark.parametrize("renew_before_s", [0.0, 2.0])
def test_an_operator_that_caps_durations_gets_one_extend_per_session_not_a_storm(
    renew_before_s: float,
) -> None:
    """60 s of wanting priority from an operator capping sessions at 20 s, each call taking 10 ms: before
    this was recognised, every capped extend was due again at once (about 2000 calls in 20 s)."""
    config = replace(CAMARA, camara=replace(CAMARA.camara, renew_before_s=renew_before_s))
    g = DroneGrant("uav1", config, 0)
    operator = CappingOperator(max_s=20)
    round_trip_ns, tick_ns = S // 100, S // 100
    now, available_ns = 0, 0
    while now < 60 * S:
        g.request(True, now // S, now)
        op = g.next_op(now)
        if op is not None:
            operator.answer(op, g, now)
            now += round_trip_ns
            continue
        if g.grant(now) is Grant.AVAILABLE:
            available_ns += tick_ns
        now += tick_ns
    sessions = operator.made
    assert sessions == math.ceil(60 / (20 - renew_before_s))  # each replaced renew_before_s before its end
    assert operator.calls[Op.EXTEND] <= sessions, operator.calls
    assert sum(operator.calls.values()) < 1000, operator.calls  # reads each second, a few calls per renewal
    assert available_ns >= 0.95 * 60 * S, available_ns / S


def test_an_extend_that_moves_the_end_is_not_a_cap_and_a_capped_session_is_renewed_before_it_ends() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(60 * S), 0)
    g.request(True, 2, 50 * S)
    assert next_op(g, 50 * S) is Op.EXTEND
    assert not g.extended(available(110 * S), 50 * S)  # moved: extended as asked
    g.request(True, 3, 100 * S)
    assert next_op(g, 100 * S) is Op.EXTEND
    assert g.extended(available(int(110.5 * S)), 100 * S)  # moved by under a second: capped
    g.request(True, 4, 105 * S)
    assert next_op(g, 105 * S) is None  # no second extend of a capped session
    assert g.next_deadline_ns(105 * S) <= 108 * S  # it wakes to renew (renew_before_s = 2)
    g.request(True, 5, int(108.5 * S))
    assert next_op(g, int(108.5 * S)) is Op.RENEW
    g.failed(Op.RENEW, "delete: 503", int(108.5 * S))
    assert next_op(g, int(108.6 * S)) is None  # a failed renewal waits before it is tried again
    g.deleted(109 * S)
    assert g.capped == ""
    assert g.next_op(109 * S) is Op.CREATE  # the successor, at once


def test_a_session_that_reached_its_duration_is_asked_for_again_without_a_back_off() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(20 * S), 0)
    g.request(True, 2, 20 * S)
    g.observed(Session("s1", QodStatus.UNAVAILABLE, "DURATION_EXPIRED", 20 * S), 20 * S)
    assert next_op(g, 20 * S) is Op.DELETE
    g.deleted(20 * S)
    assert next_op(g, 20 * S) is Op.CREATE


def test_settings_the_operator_refuses_are_not_asked_again_and_the_drone_is_told_why() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    assert g.next_op(0) is Op.CREATE
    g.refused_settings("create: 422 UNNECESSARY_IDENTIFIER: ...; fix [qos.camara.devices]")
    for t in (1, 100, 10_000):
        g.request(True, t, t * S)
        assert g.next_op(t * S) is None
        assert g.grant(t * S) is Grant.UNAVAILABLE
    g.request(False, 20_000, 20_000 * S)
    g.request(True, 20_001, 20_001 * S)  # a new episode does not forget it
    assert g.next_op(20_001 * S) is None
    assert "fix [qos.camara.devices]" in g.why()


def test_an_operators_retry_after_is_honoured_up_to_the_ceiling() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.failed(Op.CREATE, "create: 429 QUOTA_EXCEEDED", 0, retry_after_ns=120 * S)
    assert next_op(g, 119 * S) is None  # the back-off alone would have asked again after 10 s
    g.request(True, 2, 120 * S)
    assert next_op(g, 120 * S) is Op.CREATE
    g.failed(Op.CREATE, "create: 429 QUOTA_EXCEEDED", 120 * S, retry_after_ns=86_400 * S)
    g.request(True, 3, 720 * S)
    assert next_op(g, 720 * S) is Op.CREATE  # a day's Retry-After is held to ten minutes
    g.observed(available(2000 * S), 720 * S)
    g.failed(Op.POLL, "get: 429", 720 * S, retry_after_ns=30 * S)
    g.request(True, 4, 749 * S)
    assert g.next_op(749 * S) is None
    g.request(True, 5, 750 * S)
    assert g.next_op(750 * S) is Op.POLL


def test_a_withdrawn_profile_creates_nothing_keeps_the_session_held_and_asks_at_once_when_back() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.observed(available(60 * S), 0)
    g.profile_withdrawn("profile QOS_E is INACTIVE")
    assert g.grant(S) is Grant.AVAILABLE  # the session already made runs on
    assert next_op(g, S) is None
    g.request(True, 2, 60 * S)
    g.observed(Session("s1", QodStatus.UNAVAILABLE, "DURATION_EXPIRED", 60 * S), 60 * S)
    assert next_op(g, 60 * S) is Op.DELETE
    g.deleted(60 * S)
    assert next_op(g, 60 * S) is None  # no successor while the profile cannot start one
    assert (g.grant(60 * S), g.why()) == (Grant.UNAVAILABLE, "profile QOS_E is INACTIVE")
    g.request(False, 2, 61 * S)
    g.request(True, 3, 62 * S)  # a new episode is told the same, and creates nothing
    assert (next_op(g, 62 * S), g.grant(62 * S), g.why()) == (
        None,
        Grant.UNAVAILABLE,
        "profile QOS_E is INACTIVE",
    )
    g.profile_withdrawn("")
    assert next_op(g, 62 * S) is Op.CREATE  # at once, not after a back-off
    assert g.grant(62 * S) is Grant.REQUESTED


def test_a_refusal_of_the_settings_outlasts_the_profile_coming_back() -> None:
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, 0)
    g.refused_settings("fix [qos.camara.devices]")
    g.profile_withdrawn("profile QOS_E is INACTIVE")
    g.profile_withdrawn("")
    assert (next_op(g, S), g.why()) == (None, "fix [qos.camara.devices]")


def test_settings_fitted_to_a_shorter_profile_move_the_extend_and_renew_margins() -> None:
    def due(g: DroneGrant, at_s: int) -> Op | None:
        g.request(True, at_s, at_s * S)
        return next_op(g, at_s * S)

    before, fitted = DroneGrant("uav1", CAMARA, 0), DroneGrant("uav1", CAMARA, 0)  # extend 10 s before
    fitted.retime(replace(CAMARA.camara, duration_s=8, extend_before_s=4, renew_before_s=1))
    for g in (before, fitted):
        g.request(True, 0, 0)
        g.observed(available(20 * S), 0)
    assert (due(before, 11), due(fitted, 11)) == (Op.EXTEND, None)  # 9 s left
    assert due(fitted, 16) is Op.EXTEND


# ---- the declared table (OPS), row by row: each need held and not ----------------------------------------

NOW = 100 * S


def grant_in(state: SessionState, left_s: float = 60.0) -> DroneGrant:
    """A grant whose drone wants priority now, in `state`, its session (if any) just read at NOW and ending
    `left_s` later."""
    g = DroneGrant("uav1", CAMARA, 0)
    g.request(True, 1, NOW)
    status = {
        SessionState.REQUESTED: QodStatus.REQUESTED,
        SessionState.AVAILABLE: QodStatus.AVAILABLE,
        SessionState.CAPPED: QodStatus.AVAILABLE,
        SessionState.ENDED: QodStatus.UNAVAILABLE,
    }
    if state in status:
        g.observed(Session("s1", status[state], "", NOW + round(left_s * S)), NOW)
    if state is SessionState.CAPPED:
        g.capped = "s1"
    assert g.state is state
    return g


def test_the_table_has_a_row_for_each_need_and_every_state_a_row() -> None:
    assert [need for _, need, _ in OPS] == list(Need)
    assert set().union(*(states for states, _, _ in OPS)) == set(SessionState)


def test_row_create_due() -> None:
    assert grant_in(SessionState.NONE).next_op(NOW) is Op.CREATE
    unwanted = grant_in(SessionState.NONE)
    unwanted.request(False, 2, NOW)
    refused_by_arbiter = grant_in(SessionState.NONE)
    refused_by_arbiter.admit(False, "budget")
    bad_settings = grant_in(SessionState.NONE)
    bad_settings.refused_settings("fix [qos.camara.devices]")
    withdrawn = grant_in(SessionState.NONE)
    withdrawn.profile_withdrawn("profile QOS_E is INACTIVE")
    backing_off = grant_in(SessionState.NONE)
    backing_off.denied("403", NOW)
    for g in (unwanted, refused_by_arbiter, bad_settings, withdrawn, backing_off):
        assert g.next_op(NOW) is None, g.why()
    retry = NOW + round(CAMARA.camara.retry_after_denied_s * S)
    backing_off.request(True, 2, retry)  # still asking
    assert backing_off.next_op(retry) is Op.CREATE


def test_row_go_due_and_go_wait() -> None:
    ended = grant_in(SessionState.ENDED)
    revoked = grant_in(SessionState.AVAILABLE)
    revoked.admit(False, "budget")
    unwanted = grant_in(SessionState.AVAILABLE)
    unwanted.request(False, 2, NOW)
    for g in (ended, revoked):
        assert g.next_op(NOW) is Op.DELETE
    assert unwanted.next_op(NOW + 4 * S) is not Op.DELETE  # within the hold-down
    assert unwanted.next_op(NOW + 5 * S) is Op.DELETE
    ended.failed(Op.DELETE, "timeout", NOW)
    past_its_end = NOW + 61 * S  # a read would be due: the delete waiting for its retry comes first
    assert ended.next_op(NOW + S // 2) is None
    assert ended.next_op(past_its_end) is Op.DELETE
    ended.failed(Op.DELETE, "timeout", past_its_end)
    assert ended.next_op(past_its_end) is None


def test_row_read_due() -> None:
    for state in (SessionState.REQUESTED, SessionState.AVAILABLE, SessionState.CAPPED):
        g = grant_in(state)
        assert g.next_op(NOW) is None
        interval = CAMARA.camara.poll_interval_s if state is SessionState.REQUESTED else 1.0
        assert g.next_op(NOW + round(interval * S)) is Op.POLL, state


@pytest.mark.parametrize(
    ("state", "margin_s", "op"),
    [
        (SessionState.CAPPED, CAMARA.camara.renew_before_s, Op.RENEW),
        (SessionState.AVAILABLE, 10.0, Op.EXTEND),
    ],
)
def test_rows_renew_due_and_extend_due(state: SessionState, margin_s: float, op: Op) -> None:
    assert grant_in(state, left_s=margin_s).next_op(NOW) is op
    assert grant_in(state, left_s=margin_s + 0.5).next_op(NOW) is None  # not yet
    # a capped session is replaced, never extended, even within the extend margin
    assert grant_in(state, left_s=10.0).next_op(NOW) is (op if state is SessionState.AVAILABLE else None)
    unwanted = grant_in(state, left_s=margin_s)
    unwanted.request(False, 2, NOW)
    assert unwanted.next_op(NOW) is None  # released after the hold-down, not kept alive
    failed = grant_in(state, left_s=margin_s)
    failed.failed(op, "timeout", NOW)
    assert failed.next_op(NOW) is None  # waits for the failed call's retry
    assert failed.next_op(NOW + S) is Op.POLL  # its retry time is also a read's: the end is read first
