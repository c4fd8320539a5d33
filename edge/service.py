"""What every edge service shares: a stop event wired to SIGTERM/SIGINT, a health line every few
seconds, and the zenoh session as an edge client of the router."""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from types import FrameType

log = logging.getLogger(__name__)


class Service:
    def __init__(self, name: str, health_interval_s: float = 5.0) -> None:
        self.name = name
        self.stop = threading.Event()
        self.health_interval_s = health_interval_s
        self._next_health = time.monotonic() + health_interval_s

    def install_signal_handlers(self) -> None:
        def handler(signum: int, _frame: FrameType | None) -> None:
            log.info("%s: %s received, stopping", self.name, signal.Signals(signum).name)
            self.stop.set()

        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, handler)

    def maybe_health(self, line: Callable[[], str]) -> None:
        now = time.monotonic()
        if now >= self._next_health:
            self._next_health = now + self.health_interval_s
            log.info("%s health: %s", self.name, line())
