"""A report counts the flight it reports: what happened before the flight's t=0 (the take-off) is
said apart, never as the flight's."""

from __future__ import annotations

from dataclasses import replace

from dynqos.reports.markdown import _takeoff_line
from dynqos.reports.summary import _fallbacks
from tests.test_faults import _status

S = 1_000_000_000


def test_a_watchdog_tick_during_take_off_is_not_the_flights_fallback() -> None:
    climbing = replace(_status(1 * S, 20.0), fallbacks=1, fallback_s=0.2)  # a hand-over before t=0
    flying = [replace(_status(t * S, 20.0), fallbacks=1, fallback_s=0.2) for t in (3, 4, 5)]
    counted = _fallbacks([climbing, *flying], t0_ns=2 * S)
    assert counted == {
        "fallback_entered": False,
        "fallbacks": {"before_flight": 1, "in_flight": 0},
        "fallback_flown_s": 0.0,  # the climb's 0.2 s are not the flight's
    }
    summary = {"fallbacks": counted["fallbacks"]}
    assert _takeoff_line(summary) == [
        "- take-off (before t=0, not counted above): 1 hand-over(s) to the fallback"
    ]


def test_a_fallback_in_flight_is_counted_and_a_clean_take_off_says_nothing() -> None:
    statuses = [
        replace(_status(t * S, 20.0), fallbacks=n, fallback_s=flown)
        for t, n, flown in ((1, 0, 0.0), (3, 0, 0.0), (4, 1, 0.5), (5, 2, 1.3))
    ]
    counted = _fallbacks(statuses, t0_ns=2 * S)
    assert counted == {
        "fallback_entered": True,
        "fallbacks": {"before_flight": 0, "in_flight": 2},
        "fallback_flown_s": 1.3,  # as the drone counted it, whatever the statuses between said
    }
    assert _takeoff_line(counted) == []
    assert _fallbacks([], t0_ns=0)["fallback_entered"] is False
