"""libwebrtc's trendline filter in aiortc's delay-based estimator (onboard/trendline.py): it reads a queue
that keeps building as over-use, and a link that delivers in bursts without building one as normal."""

from __future__ import annotations

from collections import deque

import pytest

pytest.importorskip("aiortc", reason="the camera-rate extra (aiortc) is not installed")

from aiortc.rate import BandwidthUsage, OveruseDetector, OveruseEstimator

from dynqos.onboard.camera_rate import DelayRateControl, GccRate, new_estimator
from dynqos.onboard.trendline import GAIN, WINDOW, TrendlineEstimator, linear_fit_slope

GROUP_MS = 10  # a group sent every 10 ms


def test_the_slope_is_the_least_squares_one() -> None:
    assert linear_fit_slope(deque([(0.0, 1.0), (1.0, 3.0), (2.0, 5.0)])) == pytest.approx(2.0)
    assert linear_fit_slope(deque([(0.0, 0.0), (1.0, 1.0), (2.0, 0.0), (3.0, 1.0)])) == pytest.approx(0.2)
    assert linear_fit_slope(deque([(5.0, 1.0), (5.0, 2.0)])) is None  # one x: no line


def _detect(extra_delays_ms: list[float], kalman: bool = False) -> list[BandwidthUsage]:
    """Groups sent every 10 ms whose arrival deltas exceed that by `extra_delays_ms`: the detector's
    verdict after each (on the trendline, or on aiortc's Kalman filter)."""
    estimator = OveruseEstimator() if kalman else TrendlineEstimator()
    detector = OveruseDetector()
    now, verdicts = 0.0, []
    for extra in extra_delays_ms:
        now += GROUP_MS + extra
        estimator.update(GROUP_MS + extra, GROUP_MS, 0, detector.state(), round(now))
        verdicts.append(detector.detect(estimator.offset(), GROUP_MS, estimator.num_of_deltas(), round(now)))
    return verdicts


def test_a_queue_that_keeps_building_is_over_use_within_a_window_sooner_than_with_the_kalman_filter() -> None:
    building = [2.0] * 60  # each group 2 ms later than the last: the queue grows 200 ms/s
    verdicts, kalman = _detect(building), _detect(building, kalman=True)
    assert BandwidthUsage.OVERUSING in verdicts
    assert verdicts.index(BandwidthUsage.OVERUSING) <= WINDOW  # measured: 20 groups
    assert kalman.index(BandwidthUsage.OVERUSING) > WINDOW  # measured: 37


def test_bursts_that_build_no_queue_are_not_over_use() -> None:
    """A cellular uplink's grants: a group held 8 ms, the next delivered with it (no delay kept)."""
    for held_ms in (8.0, 20.0):
        assert BandwidthUsage.OVERUSING not in _detect([held_ms, -held_ms] * 100)
        assert BandwidthUsage.OVERUSING not in _detect([held_ms, -held_ms] * 100, kalman=True)  # nor Kalman


def test_a_steady_link_has_no_trend_and_a_draining_queue_is_under_use() -> None:
    steady = TrendlineEstimator()
    for i in range(1, 50):
        steady.update(GROUP_MS, GROUP_MS, 0, BandwidthUsage.NORMAL, i * GROUP_MS)
    assert steady.offset() == 0.0
    assert steady.num_of_deltas() == 49
    assert BandwidthUsage.UNDERUSING in _detect([2.0] * 30 + [-5.0] * 30)
    draining = TrendlineEstimator()
    now = 0
    for _ in range(WINDOW + 5):
        now += 5
        draining.update(5, GROUP_MS, 0, BandwidthUsage.NORMAL, now)
    assert draining.offset() < -GAIN * 0.5  # toward 5 ms less each 5 ms of arrivals


def test_the_rate_control_takes_the_filter_it_is_given() -> None:
    assert isinstance(new_estimator("trendline").estimator, TrendlineEstimator)
    assert not isinstance(new_estimator("kalman").estimator, TrendlineEstimator)
    control = DelayRateControl(15.0, delay_filter="trendline")
    assert isinstance(control._estimator, GccRate)
    assert isinstance(control._estimator.estimator.estimator, TrendlineEstimator)
    with pytest.raises(ValueError, match="delay_filter"):
        new_estimator("median")
