"""Mahimahi link traces as a capacity over time. Pure: the file is read once, time is passed in.

A trace lists, one per line, the millisecond at which one 1500-byte packet may leave; the trace
repeats when it ends. `bits_between(t0, t1)` is the capacity the trace grants in that span.
"""

from __future__ import annotations

import bisect
import itertools
from pathlib import Path

PACKET_BITS = 1500 * 8


class TraceError(ValueError):
    pass


class Trace:
    def __init__(self, opportunities_ms: list[int], scale: float = 1.0, source: str = "<trace>") -> None:
        if not opportunities_ms:
            raise TraceError(f"{source}: the trace has no delivery opportunities")
        if any(b < a for a, b in itertools.pairwise(opportunities_ms)):
            raise TraceError(f"{source}: timestamps must not decrease")
        if scale <= 0:
            raise TraceError(f"{source}: scale must be > 0")
        self.source = source
        self._ms = opportunities_ms
        self.period_ms = max(opportunities_ms[-1], 1)
        self.scale = scale

    @classmethod
    def load(cls, path: str | Path, *, mean_mbps: float = 0.0) -> Trace:
        """Read a trace; with mean_mbps > 0 rescale it so its mean rate is that many Mbit/s."""
        try:
            lines = Path(path).read_text(encoding="ascii").split()
        except (OSError, UnicodeDecodeError) as exc:
            raise TraceError(f"{path}: cannot read trace ({exc.__class__.__name__}: {exc})") from None
        try:
            stamps = [int(line) for line in lines]
        except ValueError as exc:
            raise TraceError(f"{path}: not a Mahimahi trace ({exc})") from None
        if any(s < 0 for s in stamps):
            raise TraceError(f"{path}: negative timestamp")
        trace = cls(stamps, source=str(path))
        if mean_mbps > 0:
            trace.scale = mean_mbps / trace.mean_mbps(unscaled=True)
        return trace

    def mean_mbps(self, *, unscaled: bool = False) -> float:
        rate = len(self._ms) * PACKET_BITS / (self.period_ms / 1000) / 1e6
        return rate if unscaled else rate * self.scale

    def _count_until(self, t_ms: float) -> float:
        periods, rest = divmod(t_ms, self.period_ms)
        return periods * len(self._ms) + bisect.bisect_right(self._ms, rest)

    def bits_between(self, t0_s: float, t1_s: float) -> float:
        """Capacity granted in [t0, t1) seconds since the trace started, scaled."""
        if t1_s <= t0_s:
            return 0.0
        count = self._count_until(t1_s * 1000) - self._count_until(t0_s * 1000)
        return count * PACKET_BITS * self.scale
