"""Driving an edge service's core as edge/runtime.py does, on a fake clock and a MemoryBus: no loop,
no thread, no zenoh."""

from __future__ import annotations

from typing import Protocol

from dynqos.common.bus import Received
from dynqos.common.queues import BoundedQueue


class Core(Protocol):
    inbox: BoundedQueue[Received]

    def handle(self, events: list[Received], now_ns: int) -> None: ...

    def tick(self, now_ns: int) -> float: ...


def take(core: Core, now_ns: int) -> None:
    """What waits in the core's inbox, handled (the runtime's turn without the tick)."""
    events = core.inbox.drain()
    if events:
        core.handle(events, now_ns)


def turn(core: Core, now_ns: int) -> float:
    """One turn of the runtime: the inbox handled, then a tick; the seconds the core asks to wait."""
    take(core, now_ns)
    return core.tick(now_ns)
