"""Small streaming statistics used by the latency monitors and the risk estimator.

Windows are bounded (a deque with maxlen), so memory never grows with run time. An empty
window reports `None`, never 0: "no samples yet" must not read as "zero latency".
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable


class SlidingWindow:
    """The last `size` samples, with their mean and percentiles."""

    __slots__ = ("_pushes", "_samples", "_sum")

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"window size must be >= 1, got {size}")
        self._samples: deque[float] = deque(maxlen=size)
        self._sum = 0.0
        self._pushes = 0

    @property
    def size(self) -> int:
        maxlen = self._samples.maxlen
        assert maxlen is not None
        return maxlen

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def full(self) -> bool:
        return len(self._samples) == self.size

    def push(self, sample: float) -> None:
        if not math.isfinite(sample):
            raise ValueError(f"sample must be finite, got {sample}")
        if self.full:
            self._sum -= self._samples[0]
        self._samples.append(sample)
        self._sum += sample
        self._pushes += 1
        if self._pushes % (self.size * 16) == 0:
            # Re-sum now and then so float error cannot accumulate over a long run.
            self._sum = math.fsum(self._samples)

    def extend(self, samples: Iterable[float]) -> None:
        for sample in samples:
            self.push(sample)

    def clear(self) -> None:
        self._samples.clear()
        self._sum = 0.0

    def mean(self) -> float | None:
        if not self._samples:
            return None
        return self._sum / len(self._samples)

    def percentile(self, q: float) -> float | None:
        """Linear-interpolated percentile, q in [0, 100] (numpy's default method)."""
        if not 0.0 <= q <= 100.0:
            raise ValueError(f"percentile must be in [0, 100], got {q}")
        if not self._samples:
            return None
        return percentile(self._samples, q)

    def values(self) -> list[float]:
        return list(self._samples)

    def last(self, n: int) -> list[float]:
        """The newest `n` samples (fewer while the window holds fewer), oldest first."""
        if n <= 0:
            return []
        samples = self._samples
        return [samples[i] for i in range(max(0, len(samples) - n), len(samples))]


def percentile(samples: Iterable[float], q: float) -> float:
    ordered = sorted(samples)
    if not ordered:
        raise ValueError("percentile of no samples")
    rank = (len(ordered) - 1) * q / 100.0
    lower = math.floor(rank)
    upper = min(lower + 1, len(ordered) - 1)
    fraction = rank - lower
    return ordered[lower] + (ordered[upper] - ordered[lower]) * fraction


class Ema:
    """First-order filter s_k = a * s_{k-1} + b * x_k; the first sample initialises s.

    With b = 1 - a this is the usual exponential moving average. The paper's risk filter keeps a
    and b separate, so both are parameters here.
    """

    __slots__ = ("_value", "a", "b")

    def __init__(self, a: float, b: float | None = None) -> None:
        if not 0.0 <= a < 1.0:
            raise ValueError(f"a must be in [0, 1), got {a}")
        self.a = a
        self.b = 1.0 - a if b is None else b
        if not (math.isfinite(self.b) and self.b > 0.0):
            raise ValueError(f"b must be finite and > 0, got {self.b}")
        self._value: float | None = None

    @property
    def value(self) -> float | None:
        return self._value

    def update(self, sample: float) -> float:
        if not math.isfinite(sample):
            raise ValueError(f"sample must be finite, got {sample}")
        if self._value is None:
            self._value = sample
        else:
            self._value = self.a * self._value + self.b * sample
        return self._value

    def reset(self) -> None:
        self._value = None
