"""Time as an injected dependency, so pure logic is tested with a clock the test controls.

Everything in dynqos measures time in integer nanoseconds of a monotonic clock. No clock
synchronisation between drone and edge is assumed anywhere (docs/architecture.md, "Time").
"""

from __future__ import annotations

import time
from typing import Protocol

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000


class Clock(Protocol):
    def now_ns(self) -> int:
        """Monotonic time in nanoseconds; only differences are meaningful."""
        ...


class MonotonicClock:
    """The process's monotonic clock (`time.monotonic_ns`)."""

    def now_ns(self) -> int:
        return time.monotonic_ns()


class FakeClock:
    """A clock that moves only when told to, for deterministic tests."""

    def __init__(self, start_ns: int = 0) -> None:
        if start_ns < 0:
            raise ValueError("start_ns must be >= 0")
        self._now_ns = start_ns

    def now_ns(self) -> int:
        return self._now_ns

    def advance_ns(self, delta_ns: int) -> int:
        if delta_ns < 0:
            raise ValueError("a monotonic clock cannot go back")
        self._now_ns += delta_ns
        return self._now_ns

    def advance_s(self, delta_s: float) -> int:
        return self.advance_ns(round(delta_s * NS_PER_S))


def seconds(ns: int) -> float:
    return ns / NS_PER_S


def to_ns(seconds_: float) -> int:
    return round(seconds_ * NS_PER_S)


def millis(ns: int) -> float:
    return ns / NS_PER_MS
