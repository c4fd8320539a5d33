"""The uplink scheduler of the emulated cell: a resource-fair scheduler with relative priority.

Every TTI the cell's capacity is shared among the backlogged users (drone bearers and virtual
background users) in proportion to their weights, each capped by what it has to send; what a user
cannot use goes to the others (weighted max-min fairness, work-conserving). This is the fluid limit
of the paper's time-domain scheduler, whose per-user weights grow while a user waits and drop when it
is served: over many TTIs each backlogged user gets capacity in proportion to its weight.

Pure code: time is passed in, nothing here does I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping


def weighted_fair_share(
    capacity: float, demands: Mapping[str, float], weights: Mapping[str, float]
) -> dict[str, float]:
    """Split `capacity` among `demands` by weight, never giving anyone more than it asked for.

    Water-filling: every round, each unsatisfied user is offered its weighted part of what remains;
    users whose residual demand is below that part take only what they need, and the rest is shared
    again among the others. Returns an allocation for every key of `demands`.
    """
    if capacity < 0 or not math.isfinite(capacity):
        raise ValueError(f"capacity must be finite and >= 0, got {capacity}")
    alloc = dict.fromkeys(demands, 0.0)
    active = {name for name, demand in demands.items() if demand > 0}
    for name in active:
        if not weights.get(name, 0.0) > 0:
            raise ValueError(f"user {name!r} needs a weight > 0")
    remaining = capacity
    while active and remaining > 1e-9:
        total_weight = sum(weights[name] for name in active)
        portions = {name: remaining * weights[name] / total_weight for name in active}
        satisfied = {name for name in active if demands[name] - alloc[name] <= portions[name]}
        if not satisfied:
            for name in active:
                alloc[name] += portions[name]
            break
        for name in satisfied:
            remaining -= demands[name] - alloc[name]
            alloc[name] = demands[name]
        active -= satisfied
    return alloc


class CapacityBucket:
    """How many bits the cell may send at a tick, from the time that really elapsed.

    asyncio timers run late and round up, so a fixed budget per tick loses capacity; instead each
    tick releases rate x elapsed time, capped at `max_ticks` TTIs so a stall cannot release a burst.
    """

    def __init__(self, tti_ns: int, max_ticks: int = 20) -> None:
        if tti_ns <= 0:
            raise ValueError("tti_ns must be > 0")
        self.tti_ns = tti_ns
        self.max_ticks = max_ticks
        self._last_ns: int | None = None

    def release(self, rate_bps: float, now_ns: int) -> float:
        if self._last_ns is None:
            self._last_ns = now_ns
            return 0.0
        elapsed_ns = min(now_ns - self._last_ns, self.max_ticks * self.tti_ns)
        self._last_ns = now_ns
        return max(0.0, rate_bps) * max(0, elapsed_ns) / 1e9


class VirtualUser:
    """A background user whose bytes need not move: a virtual backlog fed at its offered rate.

    Its backlog is capped (`max_backlog_s` of its offered rate): a real sender's buffer is finite, and
    an unbounded virtual queue would keep it backlogged long after its load stopped.
    """

    def __init__(
        self, name: str, weight: float, offered_bps: float = 0.0, max_backlog_s: float = 0.5
    ) -> None:
        self.name = name
        self.weight = weight
        self.offered_bps = offered_bps
        self.max_backlog_s = max_backlog_s
        self.backlog_bits = 0.0
        self.offered_bits = 0.0
        self.delivered_bits = 0.0

    def arrive(self, elapsed_s: float) -> None:
        bits = self.offered_bps * elapsed_s
        self.offered_bits += bits
        cap = max(self.offered_bps * self.max_backlog_s, bits)
        self.backlog_bits = min(self.backlog_bits + bits, cap)

    def serve(self, bits: float) -> None:
        served = min(bits, self.backlog_bits)
        self.backlog_bits -= served
        self.delivered_bits += served
