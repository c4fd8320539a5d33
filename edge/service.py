"""What every edge service shares: a stop event wired to SIGTERM/SIGINT, a health line every few
seconds, and the zenoh session as an edge client of the router.

The health line also goes to an optional health file, rewritten atomically each time, so that a
Kubernetes exec probe (`dynqos health FILE --max-age S`) can tell a live service from a hung one:
these services listen on no port a TCP probe could check."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from dynqos.common.bus import Bus
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError
from dynqos.common.lifecycle import ready_line, serving_metrics, stop_on_signals
from dynqos.common.metrics import ProcessMetrics

log = logging.getLogger(__name__)


class Service:
    def __init__(self, name: str, health_interval_s: float = 5.0) -> None:
        self.name = name
        self.stop = threading.Event()
        self.health_interval_s = health_interval_s
        self._next_health = time.monotonic() + health_interval_s
        self.health_file: Path | None = None
        self.beat: Callable[[str], None] | None = None  # /healthz's record of the line (common/metrics.py)

    def write_health(self, line: str) -> None:
        """Replace the health file (if any) with this line and the wall time, atomically."""
        if self.beat is not None:
            self.beat(line)
        if self.health_file is None:
            return
        record = {"service": self.name, "time_unix": time.time(), "pid": os.getpid(), "health": line}
        tmp = self.health_file.with_name(self.health_file.name + ".tmp")
        try:
            tmp.write_text(json.dumps(record) + "\n", encoding="utf-8")
            tmp.replace(self.health_file)
        except OSError as exc:
            raise DynqosError(f"cannot write health file {self.health_file}: {exc.strerror}") from None

    def install_signal_handlers(self) -> None:
        stop_on_signals(self.name, self.stop.set)

    def maybe_health(self, line: Callable[[], str]) -> None:
        now = time.monotonic()
        if now >= self._next_health:
            self._next_health = now + self.health_interval_s
            text = line()
            log.info("%s health: %s", self.name, text)
            self.write_health(text)


def check_health(path: Path, max_age_s: float, now_unix: float | None = None) -> str:
    """The health line in `path` if it was written within `max_age_s`; else DynqosError saying why."""
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        age = (time.time() if now_unix is None else now_unix) - float(record["time_unix"])
        line = f"{record['service']}: {record['health']}"
    except OSError as exc:
        raise DynqosError(f"no health file {path} ({exc.strerror}): not started yet or not writing") from None
    except (ValueError, KeyError, TypeError):
        raise DynqosError(f"{path} is not a dynqos health file") from None
    if age > max_age_s:
        raise DynqosError(f"{line}: last health {age:.1f} s ago (max {max_age_s:g} s): hung or stopped")
    return line


class Worker(Protocol):
    service: Service

    def run(self) -> Any: ...


def serve(
    name: str,
    config: Config,
    make: Callable[[Config, Bus], Worker],
    register: Callable[[Any, ProcessMetrics], None],
    *,
    health_file: Path | None = None,
) -> int:
    """Run one edge worker (MPC, planner, detector) until SIGTERM: its metrics served, its zenoh session
    open as an edge client, its health file written, one ready line; everything closed on the way out."""
    from dynqos.common.transport import Role, open_bus  # here: `dynqos health` (a probe) needs no zenoh

    with serving_metrics(name, config) as metrics, open_bus(config.zenoh, Role.EDGE) as bus:
        worker = make(config, bus)
        lifecycle = worker.service
        lifecycle.health_file = health_file
        lifecycle.beat = metrics.health.beat
        register(worker, metrics)
        lifecycle.install_signal_handlers()
        lifecycle.write_health("ready")
        ready_line(name)
        worker.run()
    return 0
