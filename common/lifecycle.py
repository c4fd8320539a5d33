"""What every long-running dynqos process does the same way at start and stop, written once: the
Prometheus endpoint served for the life of the run, SIGTERM/SIGINT turned into a stop, and the one JSON
line on stdout that says the process is ready (what the runner and the tests wait for).

Each role's `run(config, ...)` (beside the role's code) uses these; the CLI only parses and dispatches."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import signal
import sys
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

from dynqos.common.config import Config, MetricsConfig
from dynqos.common.errors import DynqosError
from dynqos.common.metrics import ProcessMetrics

log = logging.getLogger(__name__)


def ready_line(service: str, **info: Any) -> None:
    """`{"ready": true, "service": NAME, ...}` on stdout, flushed: the process serves from now on."""
    sys.stdout.write(json.dumps({"ready": True, "service": service, **info}) + "\n")
    sys.stdout.flush()


def stop_on_signals(name: str, stop: Callable[[], None]) -> None:
    """SIGTERM and SIGINT call `stop` (from the main thread, between bytecodes) and log which came."""

    def handler(signum: int, _frame: FrameType | None) -> None:
        log.info("%s: %s received, stopping", name, signal.Signals(signum).name)
        stop()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def stop_loop_on_signals(name: str, loop: asyncio.AbstractEventLoop, stop: Callable[[], None]) -> None:
    """For an asyncio process: SIGTERM and SIGINT call `stop` inside `loop` (where an asyncio.Event may be
    set) and log which came; where the loop cannot take signals (not the main thread), nothing."""

    def handler(sig: signal.Signals) -> None:
        log.info("%s: %s received, stopping", name, sig.name)
        stop()

    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, handler, sig)


def waker(loop: asyncio.AbstractEventLoop, callback: Callable[[], None]) -> Callable[[], None]:
    """What a zenoh thread calls to have `callback` run on `loop` (a BoundedQueue's `wake`): once the loop
    has closed, nothing (the process is stopping)."""

    def wake() -> None:
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(callback)

    return wake


@contextlib.contextmanager
def serving_metrics(name: str, config: Config) -> Iterator[ProcessMetrics]:
    """The process's metrics registry, its /metrics and /healthz served while the block runs ([metrics]
    port 0: registry only)."""
    metrics = ProcessMetrics(name, config.metrics)
    metrics.start()
    try:
        yield metrics
    finally:
        metrics.stop()


def with_metrics_endpoint(config: Config, port: int | None, host: str | None) -> Config:
    """`config` with its [metrics] port and host replaced by the ones given (None: keep the config's)."""
    port = config.metrics.port if port is None else port
    host = host or config.metrics.host
    try:
        metrics = MetricsConfig(port=port, host=host, stale_after_s=config.metrics.stale_after_s)
    except DynqosError as exc:
        raise DynqosError(f"--metrics-port/--metrics-host: {exc}") from None
    return dataclasses.replace(config, metrics=metrics)
