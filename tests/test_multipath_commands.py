"""A drone on two paths, answered by two edge sites: the first Command for a state is applied, the rest
are duplicates; fencing holds within each site; the setpoint step at a change of winner is measured."""

from __future__ import annotations

import itertools

import pytest

from dynqos.common.messages import Command, State, decode, encode
from dynqos.onboard.commands import CommandTracker

MS = 1_000_000


def command(
    seq: int, stamp: int, *, site: str, term: int = 1, replica: str = "", accel: float = 0.0
) -> Command:
    return Command(
        uav="uav1",
        seq=seq,
        state_seq=seq,
        state_stamp_ns=stamp,
        edge_hold_ns=0,
        dt_s=0.02,
        accel_mps2=[(accel, 0.0, 0.0)] * 10,
        yaw_rad=[0.0] * 10,
        term=term,
        replica=replica or f"mpc-{site}",
        site=site,
    )


def test_the_first_command_for_a_state_wins_and_the_other_sites_copy_is_a_duplicate() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    for seq in (1, 2, 3):
        tracker.state_sent(seq, seq * 20 * MS)
    assert tracker.offer(command(1, 20 * MS, site="a"), 45 * MS)
    assert not tracker.offer(command(1, 20 * MS, site="b"), 50 * MS)  # site B answered state 1 too
    assert not tracker.offer(command(1, 20 * MS, site="a"), 52 * MS)  # site A's copy over the other path
    assert tracker.offer(command(2, 40 * MS, site="b", term=7), 60 * MS)  # B first this time: B flies
    assert not tracker.offer(command(2, 40 * MS, site="a"), 70 * MS)
    c = tracker.counters
    assert (c.accepted, c.duplicates, c.rejected, c.site_changes, c.controller_changes) == (2, 3, 0, 1, 0)
    assert tracker.active is not None
    assert tracker.active.site == "b"
    assert tracker.controllers() == (("a", 1, "mpc-a"), ("b", 7, "mpc-b"))
    # a lost answer is not a duplicate: state 3's first Command is taken whenever it comes
    assert tracker.offer(command(3, 60 * MS, site="a"), 95 * MS)


def test_fencing_holds_within_a_site_not_across_sites() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    for seq in range(1, 6):
        tracker.state_sent(seq, seq * 20 * MS)
    assert tracker.offer(command(1, 20 * MS, site="a", term=5, replica="a1"), 30 * MS)
    # site B's term 1 is below A's 5, but terms are compared within a site only
    assert tracker.offer(command(2, 40 * MS, site="b", term=1, replica="b1"), 50 * MS)
    assert not tracker.offer(command(3, 60 * MS, site="a", term=4, replica="a2"), 70 * MS)  # fenced at A
    assert not tracker.offer(command(3, 60 * MS, site="b", term=1, replica="b2"), 70 * MS)  # B's term twice
    assert tracker.offer(command(4, 80 * MS, site="a", term=6, replica="a2"), 90 * MS)  # A's new holder
    c = tracker.counters
    assert (c.fenced, c.controller_changes) == (2, 1)
    assert tracker.controllers() == (("a", 6, "a2"), ("b", 1, "b1"))
    # an older state never answered, after a newer one was: stale, not a duplicate
    assert not tracker.offer(command(3, 60 * MS, site="a", term=6, replica="a2"), 95 * MS)
    assert (c.stale, c.duplicates) == (1, 0)


def test_the_setpoint_step_is_measured_apart_when_the_winning_site_changes() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    for seq in range(1, 5):
        tracker.state_sent(seq, seq * 20 * MS)
    tracker.offer(command(1, 20 * MS, site="a", accel=1.0), 30 * MS)
    tracker.offer(command(2, 40 * MS, site="a", accel=1.1), 50 * MS)  # a re-plan at the same site
    tracker.offer(command(3, 60 * MS, site="b", accel=1.4), 70 * MS)  # the other site wins
    tracker.offer(command(4, 80 * MS, site="b", accel=1.4), 90 * MS)
    steps = tracker.steps
    assert (steps.site_change_count, steps.site_change_max) == (1, pytest.approx(0.3))
    assert (steps.same_site_count, steps.same_site_max) == (2, pytest.approx(0.1))
    assert tracker.counters.site_changes == 1


def test_one_site_keeps_the_wire_as_it_was() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    tracker.state_sent(1, 20 * MS)
    assert tracker.offer(command(1, 20 * MS, site="", term=3, replica="m"), 30 * MS)
    assert tracker.controllers() == ()  # one unnamed site: State's command_term/replica say it all
    assert (tracker.term, tracker.replica) == (3, "m")


def test_state_and_command_carry_the_sites_on_the_wire() -> None:
    state = State(
        uav="uav1",
        seq=1,
        stamp_ns=1,
        pos_m=(0.0, 0.0, -1.0),
        vel_mps=(0.0, 0.0, 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        controllers=(("a", 2, "mpc-a"), ("b", 9, "mpc-b")),
    )
    assert decode(encode(state)) == state
    sent = command(1, 20 * MS, site="b")
    assert decode(encode(sent)).site == "b"


def test_a_site_changes_step_above_the_bound_is_eased_in_one_bound_per_period() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS, site_step_max_mps2=2.0, setpoint_period_ns=20 * MS)
    for seq in (1, 2, 3):
        tracker.state_sent(seq, seq * 20 * MS)
    tracker.offer(command(1, 20 * MS, site="a", accel=0.0), 30 * MS)
    assert tracker.offer(command(2, 40 * MS, site="b", accel=5.0), 50 * MS)  # the sites disagree by 5

    def flown(at_ms: float) -> float:
        setpoint = tracker.setpoint(round(at_ms * MS))
        assert setpoint is not None
        return setpoint.accel_mps2[0]

    # at the change and for one period: 2 of the 5; then 2 more per period, until the new plan
    assert [flown(t) for t in (50, 60, 70, 80, 90, 100, 200)] == pytest.approx([2, 2, 2, 3, 4, 5, 5])
    ticks = [flown(t) for t in range(50, 200, 20)]
    assert max(abs(b - a) for a, b in itertools.pairwise([0.0, *ticks])) <= 2.0 + 1e-9
    assert tracker.steps.site_change_max == pytest.approx(5.0)  # the sites' disagreement, as measured
    assert tracker.counters.site_steps_bounded == 1
    # a site change back, while an earlier one eases in, steps from what is flown, not from the plan
    tracker.offer(command(3, 60 * MS, site="a", accel=0.0), 75 * MS)
    assert tracker.steps.site_change_max == pytest.approx(5.0)
    assert flown(75) == pytest.approx(2.5 - 2.0)  # 2.5 was flown at 75 ms: it moves 2 towards 0
    assert flown(200) == pytest.approx(0.0)


def test_a_step_within_the_bound_or_a_replan_at_one_site_is_flown_at_once() -> None:
    for bound, site_b in ((2.0, "b"), (0.0, "b"), (2.0, "a")):  # within; no bound; the same site
        tracker = CommandTracker("uav1", watchdog_ns=150 * MS, site_step_max_mps2=bound)
        tracker.state_sent(1, 20 * MS)
        tracker.state_sent(2, 40 * MS)
        tracker.offer(command(1, 20 * MS, site="a", accel=0.0), 30 * MS)
        accel = 1.5 if bound and site_b == "b" else 5.0
        tracker.offer(command(2, 40 * MS, site=site_b, accel=accel), 50 * MS)
        setpoint = tracker.setpoint(50 * MS)
        assert setpoint is not None
        assert setpoint.accel_mps2[0] == pytest.approx(accel)
        assert (tracker.blend, tracker.counters.site_steps_bounded) == (None, 0)
