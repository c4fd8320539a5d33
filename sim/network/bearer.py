"""One bearer of the emulated cell: its TCP connections (the drone's side and the edge's), its UE
buffer, its uplink and downlink delay lines and its counters. The emulator (sim/network/cell.py) owns
the bearers, runs the TTI and decides, through the pure core, how many bits each may send; a bearer is
handed the core, the event loop and how to open the edge side of a connection when it is made.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from dynqos.common.config import BearerConfig, CellConfig
from dynqos.sim.network.cell_core import CellCore
from dynqos.sim.network.delayline import DelayLine
from dynqos.sim.network.uebuffer import UeBuffer

READ_CHUNK = 64 * 1024
SOCKET_BUFFER = 64 * 1024  # at full scale; divided by `scale` like every rate (socket_buffer_bytes)
MIN_SOCKET_BUFFER = 4096
UPSTREAM_HIGH_WATER = 256 * 1024  # edge side slow: stop granting this bearer
DOWNLINK_HIGH_WATER = 4 * 1024 * 1024

_now_ns = time.monotonic_ns


class DroneSide(asyncio.BufferedProtocol):
    """Reads the drone's bytes straight into its connection's UE buffer, never past the bound."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self._buf = bytearray(READ_CHUNK)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.conn.drone = transport
        transport.pause_reading()  # until the edge side is connected
        self.conn.bearer.open_upstream(self.conn)

    def get_buffer(self, sizehint: int) -> memoryview:
        return memoryview(self._buf)[: max(1, min(READ_CHUNK, self.conn.bearer.free_bytes()))]

    def buffer_updated(self, nbytes: int) -> None:
        self.conn.bearer.receive(self.conn, bytes(self._buf[:nbytes]))

    def connection_lost(self, exc: Exception | None) -> None:
        self.conn.close()


class EdgeSide(asyncio.Protocol):
    def __init__(self, conn: Connection) -> None:
        self.conn = conn

    def data_received(self, data: bytes) -> None:
        self.conn.bearer.downlink(self.conn, data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.conn.close()


@dataclass(eq=False)
class Connection:
    bearer: Bearer
    drone: asyncio.Transport | None = None
    edge: asyncio.Transport | None = None
    ue: UeBuffer = field(init=False)
    closed: bool = False
    reading_paused: bool = True

    def __post_init__(self) -> None:
        self.ue = UeBuffer(self.bearer.ue_capacity)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for transport in (self.drone, self.edge):
            if transport is not None:
                transport.close()
        self.bearer.forget(self)


class Bearer:
    """One QoS flow: its connections, their UE buffers, its weight, its counters."""

    def __init__(
        self,
        core: CellCore,
        loop: asyncio.AbstractEventLoop,
        open_upstream: Callable[[Connection], None],
        cfg: BearerConfig,
        cell: CellConfig,
    ) -> None:
        self.core = core
        self.loop = loop
        self.open_upstream = open_upstream  # the edge side of a new connection (the emulator's)
        self.name = cfg.name
        self.target = cfg.target_host_port
        self.ue = cfg.ue
        self.ue_capacity = cfg.ue_buffer_bytes or cell.ue_buffer_bytes
        self.connections: list[Connection] = []
        self.up_line: DelayLine[tuple[Connection, bytes]] = DelayLine(
            round(cell.base_delay_up_ms * 1e6), round(cell.jitter_ms * 1e6), seed=cell.seed
        )
        self.down_line: DelayLine[tuple[Connection, bytes]] = DelayLine(
            round(cell.base_delay_down_ms * 1e6), round(cell.jitter_ms * 1e6), seed=cell.seed + 1
        )
        self._down_tx_end_ns = 0
        self.credit_bits = 0.0
        self.listen_port = cfg.listen_port
        self.port = 0
        self.server: asyncio.Server | None = None
        self.totals = {"offered_bytes": 0, "delivered_bytes": 0, "downlink_bytes": 0, "dropped_bytes": 0}
        self.interval = dict.fromkeys(self.totals, 0)

    @property
    def granted(self) -> bool:
        """A QoD session grants this bearer its weight (with [cell] qod = true)."""
        return self.core.granted[self.name]

    def effective_weight(self) -> float:
        return self.core.effective_weight(self.name)

    def _count(self, key: str, nbytes: int) -> None:
        self.totals[key] += nbytes
        self.interval[key] += nbytes

    @property
    def buffered(self) -> int:
        return sum(c.ue.size for c in self.connections)

    def free_bytes(self) -> int:
        return max(0, self.ue_capacity - self.buffered)

    def receive(self, conn: Connection, data: bytes) -> None:
        conn.ue.append(data, _now_ns())
        self._count("offered_bytes", len(data))
        if self.free_bytes() == 0:
            self._pause_all()

    def _pause_all(self) -> None:
        for conn in self.connections:
            if conn.drone is not None and not conn.reading_paused:
                conn.drone.pause_reading()
                conn.reading_paused = True

    def resume_if_room(self) -> None:
        """Every TTI: nothing to do unless a connection's reading was paused (the usual case)."""
        if not any(conn.reading_paused for conn in self.connections):
            return
        if self.free_bytes() < min(16 * 1024, self.ue_capacity):
            return
        for conn in self.connections:
            if conn.drone is not None and conn.edge is not None and conn.reading_paused and not conn.closed:
                conn.drone.resume_reading()
                conn.reading_paused = False

    def demand_bits(self) -> float:
        if not any(c.ue.size for c in self.connections):  # every TTI, and mostly idle: no demand
            return 0.0
        writable = [c for c in self.connections if c.edge is not None and not c.closed]
        if any(c.edge.get_write_buffer_size() > UPSTREAM_HIGH_WATER for c in writable if c.edge):
            return 0.0
        return 8.0 * sum(c.ue.size for c in writable)

    def grant(self, bits: float, now_ns: int) -> None:
        """Move granted bytes from the UE buffers into the uplink delay line."""
        if bits == 0 and self.credit_bits == 0:  # nothing granted, nothing saved: nothing moves
            return
        self.credit_bits += bits
        budget = int(self.credit_bits // 8)
        for conn in self.connections:
            if budget <= 0:
                break
            if conn.ue.size == 0 or conn.edge is None:
                continue
            data = conn.ue.take(budget)
            budget -= len(data)
            self.credit_bits -= 8 * len(data)
            self.up_line.push((conn, data), len(data), now_ns)
        if self.buffered == 0:
            self.credit_bits = 0.0  # an idle bearer saves up no capacity

    def flush(self, now_ns: int) -> None:
        for conn, data in self.up_line.pop_due(now_ns):
            if not conn.closed and conn.edge is not None:
                conn.edge.write(data)
                self._count("delivered_bytes", len(data))
        if not self.core.downlink_up(now_ns):
            return  # no downlink radio: the edge's bytes wait in the cell (TCP backs the edge off)
        for conn, data in self.down_line.pop_due(now_ns):
            if not conn.closed and conn.drone is not None:
                conn.drone.write(data)
                self._count("downlink_bytes", len(data))

    def downlink(self, conn: Connection, data: bytes) -> None:
        now = _now_ns()
        rate = self.core.downlink_bps
        self._down_tx_end_ns = max(now, self._down_tx_end_ns) + round(len(data) * 8 / rate * 1e9)
        self.down_line.push((conn, data), len(data), self._down_tx_end_ns)
        if self.down_line.size > DOWNLINK_HIGH_WATER and conn.edge is not None:
            conn.edge.pause_reading()
            self.loop.call_later(0.01, self._resume_downlink, conn)

    def _resume_downlink(self, conn: Connection) -> None:
        if conn.closed or conn.edge is None:
            return
        if self.down_line.size > DOWNLINK_HIGH_WATER:
            self.loop.call_later(0.01, self._resume_downlink, conn)
        else:
            conn.edge.resume_reading()

    def queue_delay_ms(self, now_ns: int) -> float:
        ages = [age for c in self.connections if (age := c.ue.head_age_ns(now_ns)) is not None]
        return max(ages) / 1e6 if ages else 0.0

    def forget(self, conn: Connection) -> None:
        if conn in self.connections:
            self._count("dropped_bytes", conn.ue.clear())
            self.connections.remove(conn)

    def drop_connections(self) -> None:
        for conn in list(self.connections):
            conn.close()


def socket_buffer_bytes(scale: float) -> int:
    """The kernel socket buffer in front of (and behind) the emulated UE buffer. Bytes waiting in it
    are queued as surely as bytes in the UE buffer, but the emulator cannot see them; unscaled, 64 KiB on
    each side held ~0.5 s at a tenth of the rate and ~50 ms at full rate, so the scaled experiment's
    latencies were not the full-scale ones. Scaled like the rates, it holds the same time at any scale."""
    return max(MIN_SOCKET_BUFFER, round(SOCKET_BUFFER / scale))
