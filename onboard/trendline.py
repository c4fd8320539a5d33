"""libwebrtc's trendline filter for the camera's delay-based estimator. Pure.

aiortc ports the receive-side estimator of WebRTC as it was around 2016: a Kalman filter on each
group's delay variation. libwebrtc replaced it with a trendline filter (`TrendlineEstimator`,
modules/congestion_controller/goog_cc/trendline_estimator.cc): the one-way delay accumulated over the
groups, smoothed, and the slope of a least-squares line through the last 20 of them. On the traced LTE
uplinks the camera carried a fifth to two thirds of what the link could with the Kalman filter. On a
bare model of those links this filter carries 0.78 of it against 0.51-0.53; in flight, beside the
supervisor and the trace's fades, the two carried the same (docs/camera.md). It is a setting, not the
default, until a flight shows it better.

It stands in for aiortc's `OveruseEstimator` inside its `RemoteBitrateEstimator` (inter-arrival
groups, the over-use detector with its adaptive threshold, AIMD rate control are aiortc's, unchanged):
the detector multiplies `offset()` by min(deltas, 60) and compares it with its threshold, which is
what libwebrtc's trendline detector does with its modified trend (the slope times a gain of 4).
"""

from __future__ import annotations

from collections import deque
from typing import Any

WINDOW = 20  # groups in the fit (libwebrtc's kDefaultTrendlineWindowSize)
SMOOTHING = 0.9  # weight of the previous smoothed delay (kDefaultTrendlineSmoothingCoeff)
GAIN = 4.0  # the slope's gain before the threshold (kDefaultTrendlineThresholdGain)
DELTA_COUNTER_MAX = 1000


class TrendlineEstimator:
    """aiortc's `OveruseEstimator` interface (`update`, `offset`, `num_of_deltas`) on a trendline."""

    def __init__(self) -> None:
        self._num_of_deltas = 0
        self._first_arrival_ms: float | None = None
        self._accumulated_ms = 0.0
        self._smoothed_ms = 0.0
        self._history: deque[tuple[float, float]] = deque(maxlen=WINDOW)
        self._trend = 0.0

    def num_of_deltas(self) -> int:
        return self._num_of_deltas

    def offset(self) -> float:
        return self._trend * GAIN

    def update(
        self, time_delta_ms: float, timestamp_delta_ms: float, size_delta: int, hypothesis: Any, now_ms: int
    ) -> None:
        """One group's arrival delta against its send delta, arrived at `now_ms` (the receiver's)."""
        self._num_of_deltas = min(self._num_of_deltas + 1, DELTA_COUNTER_MAX)
        if self._first_arrival_ms is None:
            self._first_arrival_ms = now_ms
        self._accumulated_ms += time_delta_ms - timestamp_delta_ms
        self._smoothed_ms = SMOOTHING * self._smoothed_ms + (1 - SMOOTHING) * self._accumulated_ms
        self._history.append((now_ms - self._first_arrival_ms, self._smoothed_ms))
        if len(self._history) == WINDOW:
            slope = linear_fit_slope(self._history)
            if slope is not None:
                self._trend = slope


def linear_fit_slope(points: deque[tuple[float, float]]) -> float | None:
    """The least-squares slope of y over x; None when every x is the same."""
    n = len(points)
    mean_x = sum(x for x, _ in points) / n
    mean_y = sum(y for _, y in points) / n
    numerator = sum((x - mean_x) * (y - mean_y) for x, y in points)
    denominator = sum((x - mean_x) ** 2 for x, _ in points)
    return None if denominator == 0 else numerator / denominator
