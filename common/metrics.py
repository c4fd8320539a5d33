"""Prometheus metrics and a health endpoint for every long-running process (docs/observability.md).

Each process has its own registry and serves it, when `[metrics] port` (or `--metrics-port`) is not 0,
on `http://<host>:<port>/metrics`, beside `/healthz` for probes: 200 with the last health line while
it is fresh, 503 once it is older than `stale_after_s` (a hung loop) or before the first.

Counters that the services already keep for their health line are read at scrape time by a collector
(`Families`), so the hot paths gain nothing; histograms (RTT, camera latency, solve time) are observed
where the sample is taken. Names follow Prometheus conventions: the `dynqos_` prefix, base units in
the name (`_seconds`, `_bytes`), `_total` on counters.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from importlib import metadata
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, Gauge, Histogram, disable_created_metrics, make_wsgi_app
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from dynqos.common.bus import Bus
from dynqos.common.config import MetricsConfig
from dynqos.common.errors import DynqosError

log = logging.getLogger(__name__)

# Latency buckets (s) for the loop: 1 ms to 2 s, dense around the tens of milliseconds a loop lives in.
LATENCY_BUCKETS = (
    0.001,
    0.0025,
    0.005,
    0.0075,
    0.01,
    0.015,
    0.02,
    0.03,
    0.05,
    0.075,
    0.1,
    0.15,
    0.2,
    0.3,
    0.5,
    1.0,
    2.0,
)
SOLVE_BUCKETS = (0.0002, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1)


class HealthBeat:
    """The last health line and when it was written: what /healthz answers."""

    def __init__(self, stale_after_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.stale_after_s = stale_after_s
        self.clock = clock
        self._line = ""
        self._at: float | None = None

    def beat(self, line: str) -> None:
        self._line, self._at = line, self.clock()

    def status(self) -> tuple[bool, str]:
        if self._at is None:
            return False, "starting: no health line yet"
        age = self.clock() - self._at
        if age > self.stale_after_s:
            return False, f"stale: last health line {age:.0f} s ago: {self._line}"
        return True, self._line


class Families(Collector):
    """A collector whose metrics a function builds at scrape time from counters kept elsewhere."""

    def __init__(self, build: Callable[[], Iterable[Metric]]) -> None:
        self.build = build

    def collect(self) -> Iterator[Metric]:
        yield from self.build()


def counter(name: str, doc: str, value: float, labels: dict[str, str] | None = None) -> CounterMetricFamily:
    family = CounterMetricFamily(name, doc, labels=list(labels or {}))
    family.add_metric(list((labels or {}).values()), value)
    return family


def gauge(name: str, doc: str, value: float, labels: dict[str, str] | None = None) -> GaugeMetricFamily:
    family = GaugeMetricFamily(name, doc, labels=list(labels or {}))
    family.add_metric(list((labels or {}).values()), value)
    return family


def labelled_counter(name: str, doc: str, label: str, values: dict[str, float]) -> CounterMetricFamily:
    family = CounterMetricFamily(name, doc, labels=[label])
    for key, value in sorted(values.items()):
        family.add_metric([key], value)
    return family


def one_of(
    name: str, doc: str, label: str, choices: Iterable[str], current: str, **fixed: str
) -> GaugeMetricFamily:
    """An enum as Prometheus has it: one series per value, 1 for the current one, 0 for the others."""
    family = GaugeMetricFamily(name, doc, labels=[*fixed, label])
    for choice in choices:
        family.add_metric([*fixed.values(), choice], 1.0 if choice == current else 0.0)
    return family


def bus_families(bus: Bus) -> Iterator[Metric]:
    """Messages received and rejected (by cause) on each of a bus's subscriptions."""
    received = CounterMetricFamily(
        "dynqos_messages_received", "Messages decoded and accepted", labels=["key"]
    )
    rejected = CounterMetricFamily(
        "dynqos_messages_rejected", "Messages refused by the receive path", labels=["key", "cause"]
    )
    for stats in list(bus.subscriptions):
        received.add_metric([stats.key_expr], stats.received)
        for cause, count in sorted(dict(stats.rejected_by_cause).items()):
            rejected.add_metric([stats.key_expr, cause], count)
    yield received
    yield rejected


class ProcessMetrics:
    """One process's registry, health beat and (when configured) its HTTP endpoint."""

    def __init__(self, service: str, cfg: MetricsConfig) -> None:
        self.service = service
        self.cfg = cfg
        disable_created_metrics()  # type: ignore[no-untyped-call]  # no `_created` series: nobody reads them
        self.registry = CollectorRegistry(auto_describe=True)
        self.health = HealthBeat(cfg.stale_after_s)
        doc = "The dynqos version and service of this process"
        info = Gauge("dynqos_build_info", doc, ["version", "service"], registry=self.registry)
        info.labels(_version(), service).set(1)
        self._server: WSGIServer | None = None

    def histogram(
        self, name: str, doc: str, buckets: tuple[float, ...], labels: tuple[str, ...] = ()
    ) -> Histogram:
        return Histogram(name, doc, labels, buckets=buckets, registry=self.registry)

    def add(self, build: Callable[[], Iterable[Metric]]) -> None:
        self.registry.register(Families(build))

    def start(self) -> int | None:
        """Serve /metrics and /healthz if a port is configured; the port actually bound (None: off)."""
        if self.cfg.port == 0:
            return None
        metrics_app = make_wsgi_app(self.registry)

        def app(environ: dict[str, Any], start_response: Callable[..., Any]) -> Iterable[bytes]:
            if environ.get("PATH_INFO") == "/healthz":
                ok, text = self.health.status()
                status = "200 OK" if ok else "503 Service Unavailable"
                start_response(status, [("Content-Type", "text/plain; charset=utf-8")])
                return [f"{self.service}: {text}\n".encode()]
            return metrics_app(environ, start_response)  # type: ignore[no-any-return]

        try:
            self._server = make_server(self.cfg.host, self.cfg.port, app, handler_class=_QuietHandler)
        except OSError as exc:
            raise DynqosError(
                f"metrics: cannot listen on {self.cfg.host}:{self.cfg.port} ({exc.strerror}); "
                "choose another --metrics-port, or 0 to turn metrics off"
            ) from None
        thread = threading.Thread(target=self._server.serve_forever, name="metrics", daemon=True)
        thread.start()
        port = int(self._server.server_address[1])
        log.info("%s: metrics on http://%s:%d/metrics, health on /healthz", self.service, self.cfg.host, port)
        return port

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None


def _version() -> str:
    """The installed package's version (common/ imports nothing of the components or the CLI)."""
    try:
        return metadata.version("dynqos")
    except metadata.PackageNotFoundError:
        return "unknown"


class _QuietHandler(WSGIRequestHandler):
    """Scrapes every few seconds are not worth a log line each."""

    def log_message(self, format: str, *args: Any) -> None:
        return
