"""The emulated cell's radio as pure logic: what the uplink can carry each TTI and who gets it.

The core holds the cell's state that is not bytes: the uplink capacity (constant, from a trace, or
nothing while coverage is lost), whether the downlink is up, the background users and their backlog,
each bearer's weight (a drone's bearer has its priority weight only while a QoD session grants it), and
the timeline of events. Time comes in as `now_ns` on every call, so tests step it TTI by TTI with no
process and no clock. The shell (sim/network/cell.py) moves the bytes: it reads each bearer's demand
from its UE buffers, asks `step` for the grants, and does what an event's `Effect` says needs I/O
(dropping connections, loading a trace file, ending QoD sessions).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from dynqos.common.config import CellConfig, CellEventConfig
from dynqos.common.errors import ConfigError
from dynqos.sim.network.scheduler import CapacityBucket, VirtualUser, weighted_fair_share
from dynqos.sim.network.traces import Trace

NS_PER_S = 1_000_000_000
TRACE_WINDOW_TTIS = 20  # a late tick takes at most this many TTIs of a trace's opportunities at once


@dataclass(frozen=True, slots=True)
class Effect:
    """What an event needs from the shell besides the core's own state."""

    drop_bearers: tuple[str, ...] = ()  # close these bearers' connections (a coverage loss that drops them)
    load_trace: tuple[str, float] | None = None  # (file, mean Mbit/s): load it and hand it to `set_trace`
    end_qod: str | None = None  # the operator ends the sessions of this drone ("" = every drone's)
    profile: CellEventConfig | None = None  # the operator changes a profile (status, maxDuration)


class CellCore:
    def __init__(
        self,
        cell: CellConfig,
        bearer_weights: Mapping[str, float],
        start_ns: int,
        *,
        ue_bearers: frozenset[str] = frozenset(),
    ) -> None:
        """`bearer_weights`: each bearer's configured weight by name. With `[cell] qod`, a bearer of
        `ue_bearers` (a drone's) has more than weight 1 only while a QoD session grants it (`granted`)."""
        self.cell = cell
        self.scale = cell.scale
        self.tti_ns = round(cell.tti_ms * 1e6)
        self.uplink_bps = cell.uplink_mbps * 1e6 / cell.scale
        self.downlink_bps = cell.downlink_mbps * 1e6 / cell.scale
        self.bucket = CapacityBucket(self.tti_ns)
        self.weights = dict(bearer_weights)
        self._qod = cell.qod
        self.ue_bearers = ue_bearers
        self.granted = dict.fromkeys(bearer_weights, False)
        self._shares: dict[str, float] | None = None  # the effective weights, until one of them changes
        self.background = {
            b.name: VirtualUser(b.name, b.weight, b.offered_mbps * 1e6 / cell.scale) for b in cell.background
        }
        self.trace: Trace | None = None
        self.trace_start_ns = 0
        self.capacity_bits_total = 0.0  # what the uplink could have carried so far (scaled bits)
        self.coverage_lost_until_ns = 0
        self.downlink_lost_until_ns = 0
        self.start_ns = start_ns
        self.last_tick_ns = start_ns
        self._pending = sorted(cell.events, key=lambda e: e.at_s)
        # bearer -> the bits its resources carry per nominal bit, from its drone's radio (docs/radio.md);
        # a bearer not in it has the nominal rate
        self.rate_factors: dict[str, float] = {}

    # ---- the TTI ----------------------------------------------------------------------------------------

    @property
    def qod(self) -> bool:
        return self._qod

    @qod.setter
    def qod(self, on: bool) -> None:
        self._qod, self._shares = on, None

    def grant(self, bearer: str, granted: bool) -> None:
        """A QoD session now grants `bearer` its weight (True) or no longer does."""
        self.granted[bearer], self._shares = granted, None

    def step(self, now_ns: int, demands: Mapping[str, float]) -> dict[str, float]:
        """One TTI: the capacity since the last one shared by weight between the bearers' `demands` (bits
        waiting) and the background users (who arrive and are served here); the bits each bearer may
        send, by name (the background users' grants are in it too, under "bg:<name>"). Runs every
        millisecond: it allocates what it must and no more."""
        elapsed_s = (now_ns - self.last_tick_ns) / NS_PER_S
        capacity = self.capacity_bits(now_ns)
        self.capacity_bits_total += capacity
        self.last_tick_ns = now_ns
        if self._shares is None:
            self._shares = {name: self.effective_weight(name) for name in self.weights}
            self._shares.update({"bg:" + u.name: u.weight for u in self.background.values()})
        wants = dict(demands)
        factors = self.rate_factors
        # the scheduler shares resources: a bit sent at a poor SINR takes more of them
        for name, factor in factors.items():
            if name in wants:
                wants[name] = wants[name] / factor if factor > 0 else 0.0
        for user in self.background.values():
            user.arrive(elapsed_s)
            wants["bg:" + user.name] = user.backlog_bits
        grants = weighted_fair_share(capacity, wants, self._shares)
        for name, factor in factors.items():
            if name in grants:
                grants[name] *= factor
        for user in self.background.values():
            user.serve(grants["bg:" + user.name])
        return grants

    def capacity_bits(self, now_ns: int) -> float:
        """What the uplink carries between the last tick and `now_ns`: nothing while coverage is lost,
        a trace's opportunities, or the constant rate through a bucket that caps a late tick's burst."""
        if now_ns < self.coverage_lost_until_ns:
            self.bucket.release(0.0, now_ns)
            return 0.0
        if self.trace is not None:
            t0 = (self.last_tick_ns - self.trace_start_ns) / NS_PER_S
            t1 = (now_ns - self.trace_start_ns) / NS_PER_S
            self.bucket.release(0.0, now_ns)
            return self.trace.bits_between(max(t0, t1 - TRACE_WINDOW_TTIS * self.tti_ns / NS_PER_S), t1)
        return self.bucket.release(self.uplink_bps, now_ns)

    def effective_weight(self, bearer: str) -> float:
        weight = self.weights[bearer]
        if not self.qod or bearer not in self.ue_bearers or self.granted.get(bearer, False):
            return weight
        return min(weight, 1.0)

    def downlink_up(self, now_ns: int) -> bool:
        return now_ns >= self.downlink_lost_until_ns

    def current_capacity_mbps(self, now_ns: int) -> float:
        if now_ns < self.coverage_lost_until_ns:
            return 0.0
        if self.trace is not None:
            return self.trace.mean_mbps()
        return self.uplink_bps / 1e6

    def set_trace(self, trace: Trace | None, now_ns: int) -> None:
        """Capacity from `trace` (at full scale; scaled here) from `now_ns` on; None: the constant rate."""
        if trace is not None:
            trace.scale /= self.scale
        self.trace = trace
        self.trace_start_ns = now_ns

    # ---- events -----------------------------------------------------------------------------------------

    def due(self, now_ns: int) -> list[CellEventConfig]:
        """The timeline's events whose time has come, in order (each handed out once)."""
        elapsed_s = (now_ns - self.start_ns) / NS_PER_S
        out = []
        while self._pending and self._pending[0].at_s <= elapsed_s:
            out.append(self._pending.pop(0))
        return out

    def apply(self, event: CellEventConfig, now_ns: int) -> Effect:
        """The event's change to the radio, now; what the shell must add to it."""
        kind = event.kind
        if kind == "background":
            user = self.background.get(event.user)
            if user is None:
                raise ConfigError("user", f"unknown background user {event.user!r}")
            user.offered_bps = event.offered_mbps * 1e6 / self.scale
            if event.offered_mbps == 0:
                user.backlog_bits = 0.0
        elif kind == "capacity":
            self.uplink_bps = event.uplink_mbps * 1e6 / self.scale
            self.trace = None
        elif kind in ("coverage_loss", "downlink_loss"):
            return self._lose(event, now_ns)
        elif kind == "weight":
            if event.bearer not in self.weights:
                raise ConfigError("bearer", f"unknown bearer {event.bearer!r}")
            self.weights[event.bearer] = event.weight
            self._shares = None
        elif kind == "trace":
            return Effect(load_trace=(event.file, event.mean_mbps))
        elif kind in ("qod_end", "qod_profile"):
            if not self.qod:
                raise ConfigError("kind", f"{kind} needs [cell] qod = true")
            return Effect(end_qod=event.uav) if kind == "qod_end" else Effect(profile=event)
        return Effect()

    def _lose(self, event: CellEventConfig, now_ns: int) -> Effect:
        until = now_ns + round(event.duration_s * NS_PER_S)
        self.downlink_lost_until_ns = until
        if event.kind == "downlink_loss":
            return Effect()
        self.coverage_lost_until_ns = until
        if not event.drop_connections:
            return Effect()
        return Effect(drop_bearers=tuple(b for b in self.weights if not event.bearer or b == event.bearer))


def describe(event: CellEventConfig) -> str:
    """An event as a log line says it."""
    fields = {
        "background": f"{event.user} offers {event.offered_mbps:g} Mbit/s",
        "capacity": f"uplink {event.uplink_mbps:g} Mbit/s",
        "trace": f"trace {event.file or '(off)'}",
        "coverage_loss": f"coverage lost for {event.duration_s:g} s"
        + (" (connections dropped)" if event.drop_connections else ""),
        "downlink_loss": f"downlink lost for {event.duration_s:g} s (uplink unaffected)",
        "weight": f"bearer {event.bearer} weight {event.weight:g}",
        "qod_end": f"the network ends the QoD sessions of {event.uav or 'every drone'}",
        "qod_profile": f"the operator's profile {event.profile}: "
        + ", ".join(
            ([event.status] if event.status else [])
            + ([f"maxDuration {event.max_duration_s} s"] if event.max_duration_s else [])
        ),
    }
    return fields[event.kind]
