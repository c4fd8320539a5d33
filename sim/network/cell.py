"""The cell emulator's I/O shell: TCP listeners per bearer, the TTI timer, the bytes, the records.

Drone -> bearer listener -> UE buffer -> scheduler (each TTI) -> uplink delay line -> edge router port.
Edge -> downlink serializer (capacity) -> downlink delay line -> drone. One asyncio loop, no threads.
What the radio decides (capacity, coverage, who gets how much, the timeline's events) is the pure core
in sim/network/cell_core.py; this shell reads the clock, moves bytes and does an event's I/O.
"""

from __future__ import annotations

import asyncio
import csv
import functools
import logging
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from dynqos.common.config import BearerConfig, CellConfig, CellEventConfig
from dynqos.common.errors import ConfigError
from dynqos.sim.network.bearer import Bearer, Connection, DroneSide, EdgeSide, socket_buffer_bytes
from dynqos.sim.network.cell_core import CellCore, describe
from dynqos.sim.network.operator import Notification
from dynqos.sim.network.operator_apis import OperatorApis
from dynqos.sim.network.radio_feed import RadioFeed
from dynqos.sim.network.traces import Trace, TraceError

log = logging.getLogger(__name__)

QOD_CHECK_TICKS = 10  # sessions settle and expire at this many TTIs' resolution


_now_ns = time.monotonic_ns


class CellEmulator:
    def __init__(
        self,
        cell: CellConfig,
        bearers: tuple[BearerConfig, ...],
        out_dir: Path | None = None,
        *,
        operator: OperatorApis | None = None,
        notify: Callable[[list[Notification]], None] = lambda notes: None,
        radio: RadioFeed | None = None,
        start_ns: int | None = None,
        beat: Callable[[str], None] | None = None,
    ) -> None:
        """`operator`: the QoD API's sessions and bookings ([cell] qod = true): while it is there, a
        drone's bearer has its priority weight only while a session or booking grants it; `notify` posts
        what it tells clients; `radio`: each drone's rate from its position ([cell.radio]);
        `start_ns`: the timeline's zero (now by default); `beat`: /healthz's record, once per record."""
        self.cell = cell
        self.scale = cell.scale
        self.socket_buffer = socket_buffer_bytes(cell.scale)
        self.loop = asyncio.get_running_loop()
        self.start_ns = _now_ns() if start_ns is None else start_ns
        self.core = CellCore(
            cell,
            {b.name: b.weight for b in bearers},
            self.start_ns,
            ue_bearers=frozenset(b.name for b in bearers if b.ue),
        )
        self.core.qod = operator is not None
        self.operator = operator
        self.notify = notify
        self.radio = radio
        self.bearers = [Bearer(self.core, self.loop, self.open_upstream, b, cell) for b in bearers]
        self.background = self.core.background
        self.tti_ns = self.core.tti_ns
        self._next_record_ns = self.start_ns + round(cell.record_interval_s * 1e9)
        self._tick_handle: asyncio.TimerHandle | None = None
        self._next_tick_ns = self.start_ns
        self.stopped = asyncio.Event()
        self.ticks = 0
        self.late_ticks = 0
        self.beat = beat
        self._csv_file: TextIO | None = None
        self._csv: Any = None
        self.last_interval: dict[str, dict[str, float]] = {}
        if cell.trace:
            self._set_trace(cell.trace, cell.trace_mean_mbps, "cell.trace")
        if out_dir is not None:
            out_dir.mkdir(parents=True, exist_ok=True)
            self._csv_file = (out_dir / "cell.csv").open("w", newline="")
            self._csv = csv.writer(self._csv_file)
            self._csv.writerow(
                [
                    "t_s",
                    "name",
                    "kind",
                    "capacity_mbps",
                    "offered_bits",
                    "delivered_bits",
                    "buffer_bytes",
                    "queue_delay_ms",
                    "dropped_bytes",
                ]
            )

    # ---- set-up ------------------------------------------------------------------------------------

    def _set_trace(self, path: str, mean_mbps: float, key: str) -> None:
        trace = None
        if path:
            try:
                trace = Trace.load(path, mean_mbps=mean_mbps)
            except TraceError as exc:
                raise ConfigError(key, str(exc)) from None
        self.core.set_trace(trace, _now_ns())

    async def start(self) -> None:
        for bearer in self.bearers:
            sock = socket.socket(socket.AF_INET6 if ":" in self.cell.listen_host else socket.AF_INET)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, self.socket_buffer)
            port = bearer.listen_port
            try:
                sock.bind((self.cell.listen_host, port))
            except OSError as exc:
                sock.close()
                raise ConfigError(
                    f"bearer {bearer.name}",
                    f"cannot listen on {self.cell.listen_host}:{port} ({exc.strerror})",
                ) from None
            sock.listen(16)
            bearer.server = await self.loop.create_server(functools.partial(self._accept, bearer), sock=sock)
            bearer.port = sock.getsockname()[1]
        self._next_tick_ns = _now_ns()
        self._schedule_tick()

    def _accept(self, bearer: Bearer) -> DroneSide:
        conn = Connection(bearer)
        bearer.connections.append(conn)
        return DroneSide(conn)

    def open_upstream(self, conn: Connection) -> None:
        async def connect() -> None:
            host, port = conn.bearer.target
            try:
                transport, _ = await self.loop.create_connection(lambda: EdgeSide(conn), host, port)
            except OSError as exc:
                log.warning(
                    "bearer %s: cannot reach edge %s:%d (%s); dropping the drone's connection",
                    conn.bearer.name,
                    host,
                    port,
                    exc.strerror or exc,
                )
                conn.close()
                return
            if conn.closed:
                transport.close()
                return
            sock = transport.get_extra_info("socket")
            if sock is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.socket_buffer)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            assert isinstance(transport, asyncio.Transport)
            conn.edge = transport
            if conn.drone is not None:
                dsock = conn.drone.get_extra_info("socket")
                if dsock is not None:
                    dsock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.bearer.resume_if_room()
            log.info("bearer %s: drone connected, forwarding to %s:%d", conn.bearer.name, host, port)

        self.loop.create_task(connect())

    # ---- the TTI loop -------------------------------------------------------------------------------

    def _schedule_tick(self) -> None:
        self._next_tick_ns += self.tti_ns
        now = _now_ns()
        if self._next_tick_ns < now - 5 * self.tti_ns:  # fell behind: skip ahead, the bucket caps the burst
            self.late_ticks += 1
            self._next_tick_ns = now + self.tti_ns
        delay_s = max(0.0, (self._next_tick_ns - now) / 1e9)
        self._tick_handle = self.loop.call_at(self.loop.time() + delay_s, self._tick)

    def _tick(self) -> None:
        now = _now_ns()
        self.ticks += 1
        for event in self.core.due(now):
            self.apply(event)
        if self.operator is not None and self.ticks % QOD_CHECK_TICKS == 0:
            self.notify(self.operator.advance(self.delays_of))
            self.refresh_grants()
        grants = self.core.step(now, {bearer.name: bearer.demand_bits() for bearer in self.bearers})
        for bearer in self.bearers:
            bearer.grant(grants[bearer.name], now)
        for bearer in self.bearers:
            bearer.flush(now)
            bearer.resume_if_room()
        if now >= self._next_record_ns:
            self._record(now)
            self._next_record_ns += round(self.cell.record_interval_s * 1e9)
            if self._next_record_ns < now:
                self._next_record_ns = now + round(self.cell.record_interval_s * 1e9)
        if not self.stopped.is_set():
            self._schedule_tick()

    def delays_of(self, uav: str) -> tuple[int, int, int]:
        """The drone's packet delays now (ms): uplink (its priority bearer's queue and the uplink delay
        line), downlink and round trip, what a 5G core's QoS monitoring would measure on the flow."""
        now = _now_ns()
        queued = max((b.queue_delay_ms(now) for b in self.bearers if b.ue == uav and b.granted), default=0.0)
        up = round(self.cell.base_delay_up_ms + queued)
        down = round(self.cell.base_delay_down_ms)
        return up, down, up + down

    def refresh_grants(self) -> None:
        if self.operator is None:
            return
        for bearer in self.bearers:
            granted = bool(bearer.ue) and self.operator.granted(bearer.ue, bearer.target[1])
            if granted != bearer.granted:
                self.core.grant(bearer.name, granted)
                log.info(
                    "bearer %s: weight %g (%s)",
                    bearer.name,
                    bearer.effective_weight(),
                    "QoD session available" if granted else "no QoD session",
                )

    # ---- events -------------------------------------------------------------------------------------

    def apply(self, event: CellEventConfig) -> str:
        """Apply one event now (from the timeline or the control API); returns what was done."""
        now = _now_ns()
        effect = self.core.apply(event, now)
        if effect.load_trace is not None:
            self._set_trace(*effect.load_trace, "file")
        for bearer in self.bearers:
            if bearer.name in effect.drop_bearers:
                bearer.drop_connections()
        if self.operator is not None and (effect.end_qod is not None or effect.profile is not None):
            self.notify(self.operator.apply(effect))
            self.refresh_grants()
        text = describe(event)
        log.info("cell event at %.2f s: %s", (now - self.start_ns) / 1e9, text)
        return text

    # ---- records and counters -----------------------------------------------------------------------

    def current_capacity_mbps(self, now_ns: int) -> float:
        return self.core.current_capacity_mbps(now_ns)

    def _record(self, now_ns: int) -> None:
        """One record per bearer and background user for the interval that just ended."""
        t_s = f"{(now_ns - self.start_ns) / 1e9:.3f}"
        capacity = f"{self.current_capacity_mbps(now_ns):.3f}"
        interval_s = self.cell.record_interval_s
        rows: list[list[Any]] = []
        for bearer in self.bearers:
            offered_bits = bearer.interval["offered_bytes"] * 8
            delivered_bits = bearer.interval["delivered_bytes"] * 8
            delay_ms = bearer.queue_delay_ms(now_ns)
            self.last_interval[bearer.name] = {
                "offered_mbps": offered_bits / interval_s / 1e6,
                "delivered_mbps": delivered_bits / interval_s / 1e6,
                "buffer_bytes": bearer.buffered,
                "queue_delay_ms": delay_ms,
            }
            rows.append(
                [
                    t_s,
                    bearer.name,
                    "bearer",
                    capacity,
                    offered_bits,
                    delivered_bits,
                    bearer.buffered,
                    f"{delay_ms:.3f}",
                    bearer.interval["dropped_bytes"],
                ]
            )
            bearer.interval = dict.fromkeys(bearer.interval, 0)
        for user in self.background.values():
            previous = self.last_interval.get("bg:" + user.name, {})
            bg_offered = user.offered_bits - previous.get("offered_bits_total", 0.0)
            bg_delivered = user.delivered_bits - previous.get("delivered_bits_total", 0.0)
            self.last_interval["bg:" + user.name] = {
                "offered_bits_total": user.offered_bits,
                "delivered_bits_total": user.delivered_bits,
                "offered_mbps": bg_offered / interval_s / 1e6,
                "delivered_mbps": bg_delivered / interval_s / 1e6,
                "backlog_bits": user.backlog_bits,
            }
            rows.append(
                [
                    t_s,
                    user.name,
                    "background",
                    capacity,
                    round(bg_offered),
                    round(bg_delivered),
                    round(user.backlog_bits / 8),
                    "",
                    0,
                ]
            )
        if self._csv is not None and self._csv_file is not None:
            self._csv.writerows(rows)
            self._csv_file.flush()
        if self.beat is not None:
            self.beat(f"ticks={self.ticks} late_ticks={self.late_ticks} capacity_mbps={capacity}")

    def counters(self) -> dict[str, Any]:
        now = _now_ns()
        return {
            "t_s": (now - self.start_ns) / 1e9,
            "scale": self.scale,
            "capacity_mbps": self.current_capacity_mbps(now),
            "capacity_bits": self.core.capacity_bits_total,
            "ticks": self.ticks,
            "late_ticks": self.late_ticks,
            "bearers": {
                b.name: {
                    "port": b.port,
                    "weight": b.effective_weight(),
                    "granted": b.granted,
                    "connections": len(b.connections),
                    "buffer_bytes": b.buffered,
                    "queue_delay_ms": b.queue_delay_ms(now),
                    **b.totals,
                    "last_interval": self.last_interval.get(b.name, {}),
                }
                for b in self.bearers
            },
            "background": {
                u.name: {
                    "weight": u.weight,
                    "offered_mbps_now": u.offered_bps * self.scale / 1e6,
                    "offered_bits": u.offered_bits,
                    "delivered_bits": u.delivered_bits,
                    "backlog_bits": u.backlog_bits,
                    "last_interval": self.last_interval.get("bg:" + u.name, {}),
                }
                for u in self.background.values()
            },
            **({"radio": self.radio.counters()} if self.radio is not None else {}),
        }

    async def stop(self) -> None:
        self.stopped.set()
        if self._tick_handle is not None:
            self._tick_handle.cancel()
        for bearer in self.bearers:
            if bearer.server is not None:
                bearer.server.close()
            bearer.drop_connections()
        self._record(_now_ns())
        if self._csv_file is not None:
            self._csv_file.close()
