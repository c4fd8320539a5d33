"""A delay line: what enters at t leaves at t + base delay + jitter, in order. Pure; time passed in."""

from __future__ import annotations

import random
from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")


class DelayLine(Generic[T]):
    def __init__(self, base_delay_ns: int, jitter_ns: int = 0, seed: int = 0) -> None:
        if base_delay_ns < 0 or jitter_ns < 0:
            raise ValueError("delays must be >= 0")
        self.base_delay_ns = base_delay_ns
        self.jitter_ns = jitter_ns
        self._rng = random.Random(seed)
        self._items: deque[tuple[int, int, T]] = deque()
        self._last_due_ns = 0
        self.size = 0  # sum of the sizes of what is inside

    def __len__(self) -> int:
        return len(self._items)

    def push(self, item: T, size: int, now_ns: int) -> int:
        """Enqueue; returns the due time. Order is kept: jitter never lets an item overtake."""
        jitter = self._rng.uniform(-self.jitter_ns, self.jitter_ns) if self.jitter_ns else 0.0
        due = max(now_ns + max(0, round(self.base_delay_ns + jitter)), self._last_due_ns)
        self._last_due_ns = due
        self._items.append((due, size, item))
        self.size += size
        return due

    def pop_due(self, now_ns: int) -> list[T]:
        out = []
        while self._items and self._items[0][0] <= now_ns:
            _, size, item = self._items.popleft()
            self.size -= size
            out.append(item)
        return out

    def next_due_ns(self) -> int | None:
        return self._items[0][0] if self._items else None

    def clear(self) -> int:
        dropped = self.size
        self._items.clear()
        self.size = 0
        return dropped
