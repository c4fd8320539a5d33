"""Bounded hand-offs between zenoh callback threads and the code that consumes what they deliver.

Zenoh callbacks must never block, so `put` never waits: when the queue is full the oldest item is
dropped (the newest state or command is the one worth having) and the drop is counted. Token changes
(a replica or a drone came or went) wait in `PendingChanges`: the newest per key, a flood of new keys
beyond the bound refused and counted.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
K = TypeVar("K")


class BoundedQueue(Generic[T]):
    """`wake`, when set, is called (outside the lock, on the putting thread) by a put into an empty
    queue: an event loop's consumer schedules one drain per wake (`loop.call_soon_threadsafe`) instead
    of a thread blocking in `get` to forward each item."""

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen must be >= 1, got {maxlen}")
        self._items: deque[T] = deque(maxlen=maxlen)
        self._ready = threading.Condition()
        self.dropped = 0
        self.put_count = 0
        self.wake: Callable[[], None] | None = None

    def __len__(self) -> int:
        return len(self._items)

    def put(self, item: T) -> None:
        with self._ready:
            first = not self._items
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append(item)
            self.put_count += 1
            self._ready.notify()
        if first and self.wake is not None:
            self.wake()

    def get(self, timeout_s: float | None = None) -> T | None:
        """The oldest item, waiting up to timeout_s (None: forever); None on timeout."""
        with self._ready:
            if not self._ready.wait_for(lambda: len(self._items) > 0, timeout=timeout_s):
                return None
            return self._items.popleft()

    def get_nowait(self) -> T | None:
        with self._ready:
            return self._items.popleft() if self._items else None

    def drain(self) -> list[T]:
        with self._ready:
            items = list(self._items)
            self._items.clear()
            return items


class PendingChanges(Generic[K]):
    """Whether each key is alive now, as zenoh's thread last said, until the worker takes them all."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.refused = 0  # new keys offered while `limit` others waited
        self._pending: dict[K, bool] = {}
        self._lock = threading.Lock()

    def offer(self, key: K, alive: bool) -> bool | None:
        """Note a change; returns whether nothing else was waiting (time to wake the worker), None if
        refused."""
        with self._lock:
            if key not in self._pending and len(self._pending) >= self.limit:
                self.refused += 1
                return None
            first = not self._pending
            self._pending[key] = alive
            return first

    def take(self) -> dict[K, bool]:
        with self._lock:
            changes, self._pending = self._pending, {}
        return changes
