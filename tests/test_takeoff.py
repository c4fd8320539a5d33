"""The take-off and the exit, decided by onboard/takeoff.py on a made-up clock: each step, each wait,
each refusal, with no FC and no thread."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from dynqos.onboard.fc import FcState
from dynqos.onboard.takeoff import (
    ARM_RETRY_S,
    ARM_WINDOW_S,
    CLIMB_TIMEOUT_S,
    COMMAND_ATTEMPTS,
    DISARM_GRACE_S,
    NO_ALTITUDE,
    PRIME_SETPOINTS,
    TRANSITIONS,
    Do,
    Event,
    ExitAction,
    Phase,
    TakeoffSequencer,
    on_exit,
)

S = 1_000_000_000


def at(alt_m: float) -> FcState:
    return FcState(stamp_ns=0, pos_m=(1.0, 2.0, -alt_m), vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0))


def test_arm_take_off_climb_prime_and_offboard_in_order() -> None:
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=10.0, start_ns=0)
    assert seq.next(0, None, fc_heard=False).do is Do.WAIT  # no FC yet
    assert seq.next(1 * S, at(0.0), fc_heard=True).do is Do.TAKEOFF_ALTITUDE  # before arming
    seq.answered(0)
    assert seq.next(1 * S, at(0.0), fc_heard=True).do is Do.ARM
    seq.answered(0)
    assert seq.next(1 * S, at(0.0), fc_heard=True).do is Do.TAKE_OFF
    seq.answered(0)
    climbing = seq.next(2 * S, at(1.0), fc_heard=True)
    assert (climbing.do, climbing.wait_s > 0) == (Do.WAIT, True)
    assert seq.next(3 * S, at(1.9), fc_heard=True).do is Do.HOLD_SETPOINT  # within 0.15 m of 2 m
    primes = [seq.next(3 * S, at(2.0), fc_heard=True) for _ in range(PRIME_SETPOINTS - 1)]
    assert {p.do for p in primes} == {Do.HOLD_SETPOINT}
    assert {p.hold for p in primes} == {at(1.9)}  # they hold where the climb ended
    assert seq.next(3 * S, at(2.0), fc_heard=True).do is Do.OFFBOARD
    seq.answered(0)
    done = seq.next(3 * S, at(2.0), fc_heard=True)
    assert (done.do, done.hold) == (Do.DONE, at(1.9))


def test_a_silent_fc_fails_after_its_timeout_and_the_failure_sticks() -> None:
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    assert seq.next(4 * S, at(0.0), fc_heard=False).do is Do.WAIT  # a position but no heartbeat
    failed = seq.next(5 * S, None, fc_heard=False)
    assert failed.do is Do.FAILED
    assert "no heartbeat" in failed.reason
    assert seq.next(6 * S, at(0.0), fc_heard=True).do is Do.FAILED


def test_each_refusal_ends_the_take_off_with_what_was_refused() -> None:
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    for _ in range(2):  # the altitude, the arming
        seq.next(0, at(0.0), fc_heard=True)
        seq.answered(0)
    assert seq.next(0, at(0.0), fc_heard=True).do is Do.TAKE_OFF
    seq.answered(4)  # MAV_RESULT_FAILED
    refused = seq.next(0, at(0.0), fc_heard=True)
    assert refused.reason == "the flight controller refused to take off (answered 4)"
    assert seq.refusals == ["the flight controller answered 4 to 'take off'"]
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    while seq.next(0, at(2.0), fc_heard=True).do is not Do.OFFBOARD:
        seq.answered(0)
    for _ in range(COMMAND_ATTEMPTS):
        seq.answered(None)  # no answer in time, each time
        step = seq.next(0, at(2.0), fc_heard=True)
    assert step.reason == (
        f"the flight controller refused offboard mode (did not answer {COMMAND_ATTEMPTS} times)"
    )


def test_a_command_without_an_answer_is_sent_again_with_its_confirmation_counted() -> None:
    """MAVLink's command protocol: no COMMAND_ACK in time, the same command again with confirmation 1,
    2, ...; one lost datagram on a busy link (seen: 1 of 15 fleet runs stayed on the ground) is no
    refusal. An answer after the retransmissions goes on as if the first had been answered."""
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    seq.next(0, at(0.0), fc_heard=True)
    seq.answered(0)  # the take-off altitude
    first = seq.next(0, at(0.0), fc_heard=True)
    assert (first.do, first.confirmation) == (Do.ARM, 0)
    seq.answered(None)
    again = seq.next(0, at(0.0), fc_heard=True)
    assert (again.do, again.confirmation) == (Do.ARM, 1)
    seq.answered(0)
    take_off = seq.next(0, at(0.0), fc_heard=True)
    assert (take_off.do, take_off.confirmation) == (Do.TAKE_OFF, 0)


def test_a_climb_that_never_reaches_the_altitude_goes_on_after_its_timeout() -> None:
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    for _ in range(3):
        seq.next(0, at(0.0), fc_heard=True)
        seq.answered(0)
    assert seq.next(1 * S, at(1.0), fc_heard=True).do is Do.WAIT  # the climb's clock starts here
    assert seq.next(int((1 + CLIMB_TIMEOUT_S) * S) - 1, at(1.0), fc_heard=True).do is Do.WAIT
    step = seq.next(int((1 + CLIMB_TIMEOUT_S) * S), at(1.2), fc_heard=True)
    assert (step.do, step.hold) == (Do.HOLD_SETPOINT, at(1.2))


def test_a_refused_arming_is_asked_again_each_second_until_its_window_closes() -> None:
    """PX4 refuses to arm until its estimator has a heading, a few seconds after boot; it says why in
    STATUSTEXT and arms when asked again."""
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    seq.next(0, at(0.0), fc_heard=True)
    seq.answered(0)
    assert seq.next(0, at(0.0), fc_heard=True).do is Do.ARM
    seq.answered(1)  # MAV_RESULT_TEMPORARILY_REJECTED
    wait = seq.next(0, at(0.0), fc_heard=True)
    assert (wait.do, wait.wait_s) == (Do.WAIT, ARM_RETRY_S)
    assert seq.next(int(ARM_RETRY_S * S), at(0.0), fc_heard=True).do is Do.ARM
    seq.answered(0)
    assert seq.next(int(ARM_RETRY_S * S), at(0.0), fc_heard=True).do is Do.TAKE_OFF
    assert seq.refusals == ["the flight controller answered 1 to 'arm'"]

    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    seq.next(0, at(0.0), fc_heard=True)
    seq.answered(0)
    t = 0
    while (step := seq.next(t, at(0.0), fc_heard=True)).do is not Do.FAILED:
        if step.do is Do.ARM:
            seq.answered(2)  # MAV_RESULT_DENIED, every time
        t += int(ARM_RETRY_S * S)
    assert step.reason == "the flight controller refused to arm (answered 2)"
    assert ARM_WINDOW_S * S <= t <= (ARM_WINDOW_S + 2 * ARM_RETRY_S) * S


def test_an_fc_that_disarms_during_the_climb_ends_the_take_off() -> None:
    """PX4 disarms an armed vehicle that has not taken off within COM_DISARM_PRFLT: a take-off that
    went nowhere must not go on to offboard mode on the ground."""
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    for _ in range(3):
        seq.next(0, at(0.0), fc_heard=True, armed=True)
        seq.answered(0)
    assert seq.next(1 * S, at(0.0), fc_heard=True, armed=False).do is Do.WAIT  # the heartbeat may lag
    failed = seq.next(int((1 + DISARM_GRACE_S) * S), at(0.0), fc_heard=True, armed=False)
    assert (failed.do, failed.reason) == (Do.FAILED, "the flight controller disarmed during the climb")


def test_an_fc_that_never_confirms_the_take_off_altitude_still_takes_off_to_its_own() -> None:
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    for _ in range(COMMAND_ATTEMPTS):
        assert seq.next(0, at(0.0), fc_heard=True).do is Do.TAKEOFF_ALTITUDE
        seq.answered(None)
    assert seq.next(0, at(0.0), fc_heard=True).do is Do.ARM
    assert seq.refusals == [NO_ALTITUDE]


def test_only_a_drone_flying_from_the_edge_is_handed_a_mode_when_the_daemon_stops() -> None:
    assert on_exit(offloading=False, on_exit_setting="land") is ExitAction.NOTHING
    assert on_exit(offloading=True, on_exit_setting="land") is ExitAction.LAND
    assert on_exit(offloading=True, on_exit_setting="hold") is ExitAction.HOLD


# ---- the table, row by row -----------------------------------------------------------------------------


def _reach(phase: Phase) -> TakeoffSequencer:
    """A sequencer brought to `phase` by an FC that accepts everything, at t = 0 (the climb at 1 s)."""
    seq = TakeoffSequencer(altitude_m=2.0, fc_timeout_s=5.0, start_ns=0)
    order = [Phase.ALTITUDE, Phase.ARM, Phase.TAKE_OFF, Phase.CLIMB]
    if phase is Phase.WAIT_FC:
        return seq
    seq.next(0, at(0.0), fc_heard=True)
    for reached in order:
        if seq.phase is phase:
            return seq
        if phase is Phase.ARM_AGAIN and seq.phase is Phase.ARM:
            seq.answered(1)
            return seq
        seq.answered(0)
        if reached is not Phase.TAKE_OFF:
            seq.next(0, at(0.0), fc_heard=True)
    for _ in range(PRIME_SETPOINTS + 1):  # climbed: the hold setpoints, then offboard is asked for
        seq.next(1 * S, at(2.0), fc_heard=True)
        if seq.phase is phase:
            return seq
    raise AssertionError(f"{phase} not reached: {seq.phase}")


def _unanswered(seq: TakeoffSequencer) -> None:
    for _ in range(COMMAND_ATTEMPTS):
        seq.answered(None)
        if seq.phase in (Phase.ALTITUDE, Phase.ARM, Phase.TAKE_OFF, Phase.OFFBOARD):
            seq.next(0, at(2.0), fc_heard=True)


def _arm_refused_late(seq: TakeoffSequencer) -> None:
    seq.answered(1)  # the first refusal, at 0: asked again after ARM_RETRY_S ...
    late = int((ARM_WINDOW_S + 1) * S)
    assert seq.next(late, at(0.0), fc_heard=True).do is Do.ARM
    seq.answered(1)  # ... and refused once the window has closed


def _climb_then(seq: TakeoffSequencer, after_s: float, fc: FcState | None, armed: bool | None = None) -> None:
    seq.next(1 * S, at(1.0), fc_heard=True, armed=armed)  # the climb's clock starts
    seq.next(int((1 + after_s) * S), fc, fc_heard=True, armed=armed)


def _retry_due(seq: TakeoffSequencer) -> None:
    seq.next(int(ARM_RETRY_S * S), at(0.0), fc_heard=True)


def _disarmed(seq: TakeoffSequencer) -> None:
    _climb_then(seq, DISARM_GRACE_S, at(0.0), armed=False)


def _prime(seq: TakeoffSequencer) -> None:
    for _ in range(PRIME_SETPOINTS):  # one was sent on the way here
        seq.next(1 * S, at(2.0), fc_heard=True)


# Each transition: how the test makes it happen, and where the take-off must then be (written here, not
# read from the table, so that a row changed by mistake fails).
DRIVE: dict[tuple[Phase, Event], tuple[Callable[[TakeoffSequencer], object], Phase]] = {
    (Phase.WAIT_FC, Event.FC_HEARD): (lambda seq: seq.next(0, at(0.0), fc_heard=True), Phase.ALTITUDE),
    (Phase.WAIT_FC, Event.FC_SILENT): (lambda seq: seq.next(5 * S, None, fc_heard=False), Phase.FAILED),
    (Phase.ALTITUDE, Event.ACCEPTED): (lambda seq: seq.answered(0), Phase.ARM),
    (Phase.ALTITUDE, Event.REFUSED): (lambda seq: seq.answered(4), Phase.ARM),
    (Phase.ALTITUDE, Event.UNANSWERED): (_unanswered, Phase.ARM),
    (Phase.ALTITUDE, Event.FC_SILENT): (lambda seq: seq.next(6 * S, at(0.0), fc_heard=False), Phase.FAILED),
    (Phase.ARM, Event.ACCEPTED): (lambda seq: seq.answered(0), Phase.TAKE_OFF),
    (Phase.ARM, Event.REFUSED_EARLY): (lambda seq: seq.answered(1), Phase.ARM_AGAIN),
    (Phase.ARM, Event.REFUSED): (_arm_refused_late, Phase.FAILED),
    (Phase.ARM, Event.UNANSWERED): (_unanswered, Phase.FAILED),
    (Phase.ARM, Event.FC_SILENT): (lambda seq: seq.next(6 * S, None, fc_heard=True), Phase.FAILED),
    (Phase.ARM_AGAIN, Event.RETRY_DUE): (
        _retry_due,
        Phase.ARM,
    ),
    (Phase.ARM_AGAIN, Event.FC_SILENT): (lambda seq: seq.next(6 * S, at(0.0), fc_heard=False), Phase.FAILED),
    (Phase.TAKE_OFF, Event.ACCEPTED): (lambda seq: seq.answered(0), Phase.CLIMB),
    (Phase.TAKE_OFF, Event.REFUSED): (lambda seq: seq.answered(4), Phase.FAILED),
    (Phase.TAKE_OFF, Event.UNANSWERED): (_unanswered, Phase.FAILED),
    (Phase.CLIMB, Event.CLIMBED): (lambda seq: seq.next(1 * S, at(1.9), fc_heard=True), Phase.PRIME),
    (Phase.CLIMB, Event.CLIMB_TIMEOUT): (lambda seq: _climb_then(seq, CLIMB_TIMEOUT_S, at(1.0)), Phase.PRIME),
    (Phase.CLIMB, Event.POSITION_LOST): (lambda seq: _climb_then(seq, CLIMB_TIMEOUT_S, None), Phase.FAILED),
    (Phase.CLIMB, Event.DISARMED): (
        _disarmed,
        Phase.FAILED,
    ),
    (Phase.PRIME, Event.PRIMED): (
        _prime,
        Phase.OFFBOARD,
    ),
    (Phase.OFFBOARD, Event.ACCEPTED): (lambda seq: seq.answered(0), Phase.DONE),
    (Phase.OFFBOARD, Event.REFUSED): (lambda seq: seq.answered(4), Phase.FAILED),
    (Phase.OFFBOARD, Event.UNANSWERED): (_unanswered, Phase.FAILED),
}


def test_every_row_of_the_table_has_its_own_test_below() -> None:
    assert set(DRIVE) == set(TRANSITIONS)


@pytest.mark.parametrize(("phase", "event"), list(TRANSITIONS), ids=lambda x: x.name)
def test_each_transition_leads_where_the_table_says(phase: Phase, event: Event) -> None:
    seq = _reach(phase)
    assert seq.phase is phase
    drive, expected = DRIVE[(phase, event)]
    drive(seq)
    assert seq.phase is expected
    if seq.phase is Phase.FAILED:
        assert seq.failed
        assert seq.next(10**12, at(2.0), fc_heard=True).do is Do.FAILED  # a failure sticks
