"""The preflight's clock-offset estimate (onboard/clock_offset.py): NTP's midpoint rule on the probe with
the shortest round trip. The probes through a real router: tests/test_secure_zenoh.py and
tests/test_onboard_check.py."""

from __future__ import annotations

import pytest

from dynqos.onboard.clock_offset import Probe, estimate

MS = 1_000_000


def test_no_probe_gives_no_estimate() -> None:
    assert estimate([]) is None


def test_the_router_ahead_by_30_ms_reads_plus_30_within_half_the_round_trip() -> None:
    # sent at 0, stamped by a router 30 ms ahead 2 ms later, back at 4 ms (the drone's clock)
    found = estimate([Probe(0, 32 * MS, 4 * MS)])
    assert found is not None
    assert found.offset_ms == pytest.approx(30.0)
    assert found.error_ms == pytest.approx(2.0)


def test_the_probe_with_the_shortest_round_trip_counts_not_the_first_or_the_mean() -> None:
    queued = Probe(0, 40 * MS - 30 * MS, 50 * MS)  # waited 40 ms on the way there: reads -15 ms
    quick = Probe(100 * MS, 101 * MS - 20 * MS, 102 * MS)  # the router 20 ms behind
    found = estimate([queued, quick])
    assert found is not None
    assert found.offset_ms == pytest.approx(-20.0)
    assert found.error_ms == pytest.approx(1.0)
