"""`dynqos edge mpc`: one process, one controller per drone, found by the drones' presence tokens.

Zenoh callbacks only decode and queue into the runtime's inbox (edge/runtime.py); the core keeps the
newest state per drone, solves and publishes the Command (REAL_TIME, express) on the runtime's loop.
A failed solve sends nothing and is counted; the drone's watchdog takes over. Idle drones are
dropped after `idle_timeout_s`.

Any number of processes may run side by side: each declares a liveliness token, and edge/replicas.py
decides from the live set which one flies each drone (the next one stands by for it, keeping the
drone's newest state, and takes over when its token goes or its heartbeat stops for
`takeover_after_s`: the beat, sent from the loop every fifth of that, says the loop still turns).
Commands carry the replica's term, which the drone uses to refuse a replaced one; a standby learns
who flies a drone from the drone's own States (the term and replica it follows), not from the
commands, which it no longer receives (docs/reliability.md).
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import cast

import numpy as np
from prometheus_client import Histogram

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher, RawBus, Received
from dynqos.common.config import Config
from dynqos.common.keys import Downlink
from dynqos.common.messages import Command, Reference, State
from dynqos.edge import feeds, metrics
from dynqos.edge.feeds import DroneFeeds
from dynqos.edge.membership import Membership, default_replica_id
from dynqos.edge.mpc.controller import DroneController
from dynqos.edge.mpc.problem import SolveError
from dynqos.edge.replicas import MAX_REPLICAS, Assignment, Role
from dynqos.edge.runtime import EdgeCore, Ports, serve

log = logging.getLogger(__name__)

MAX_PATHS = 8  # later copies of one State kept until it is answered (a drone has a few paths)
BEATS_PER_LEASE = 5  # a holder beats five times per lease: four late or lost beats are no takeover;
# a standby watches as often (a takeover is at most a fifth of the lease late: 10 ms at 50 ms)
IDLE_TURN_NS = 100_000_000  # with no drone, the loop turns ten times a second


@dataclass
class MpcCounters:
    states: int = 0
    commands: int = 0
    stale: int = 0
    solve_failures: int = 0
    references: int = 0
    other_shard: int = 0
    not_mine: int = 0  # states of drones this replica neither flies nor stands by for
    copies: int = 0  # a State's later copies by another path, each answered with the same Command
    solve_ms: list[float] = field(default_factory=list)


def shard_of(uav: str, shard_count: int) -> int:
    """The MPC replica that serves `uav`: stable across processes and restarts (unlike hash())."""
    return zlib.crc32(uav.encode()) % shard_count


class MpcService(EdgeCore):
    name = "mpc"

    def __init__(self, config: Config, ports: Ports) -> None:
        bus = ports.bus
        self.config = config
        self.bus = bus
        self.clock = ports.clock
        self.controllers: dict[str, DroneController] = {}
        self.publishers: dict[str, Publisher] = {}
        self.inbox = ports.inbox
        self.counters = MpcCounters()
        cfg = config.mpc
        self.replica = cfg.replica_id or default_replica_id()
        self.assignment = Assignment(
            self.replica,
            lease_ns=round(cfg.takeover_after_s * 1e9),
            holdoff_ns=round(cfg.holdoff_s * 1e9),
            beats=True,
        )
        self.newest: dict[str, Received] = {}  # the newest state per drone we stand by for
        # A drone on two paths sends each State by both (docs/multipath.md): the first copy is solved and
        # each later copy gets the same Command under its own path, so the drone times each uplink.
        self._copies: dict[str, list[Received]] = {}  # later copies of the newest state, not answered yet
        self._answered: dict[str, Command] = {}  # the last Command sent to each drone
        self._paths_heard: dict[str, set[str]] = {}  # the paths the newest state came by
        # Once per beat period, and at once when the live set changed, a replica watches: it reads the
        # newest states of the drones it stands by for, and scans every drone's seat for a takeover due
        # and an idle drone (a scan per state cost 17 us at 100 drones).
        self._next_watch_ns = 0
        # Replicas of one static shard (or all, unsharded) share its drones among themselves; with sites,
        # within their site only: each site answers every drone (docs/multipath.md).
        group = "all" if cfg.shard_count == 1 else f"shard-{cfg.shard_index}-of-{cfg.shard_count}"
        group = f"site-{cfg.site}-{group}" if cfg.site else group
        self.membership = Membership("mpc", group, self.assignment, bus)
        # The replicas' heartbeats: each beat's arrival noted on zenoh's thread (the newest per replica,
        # a bounded map), handed to the assignment on the loop.
        self._beat = bus.publisher(
            keys.replica_beat("mpc", group, self.replica), Priority.REAL_TIME, express=True
        )
        self._beat_period_ns = round(cfg.takeover_after_s * 1e9 / BEATS_PER_LEASE)
        self._next_beat_ns = 0
        self._turn_gap_ns = IDLE_TURN_NS  # the longest our loop asked to wait before its next turn
        self._beats_heard: dict[str, int] = {}
        cast(RawBus, bus).raw_subscribe(keys.replica_beats("mpc", group), self._on_beat, direct=True)
        # Each drone's state and its references (its holder's commands are no standby's business). A
        # drone it stands by for has its states kept newest-only in zenoh and read once per beat period:
        # decoded and queued one by one, they cost a standby most of what serving costs
        # (docs/benchmarks.md, `edge_scale`).
        self.feeds = DroneFeeds("mpc", bus, self.inbox, [feeds.states(pullable=True), feeds.references()])
        self.feeds.reconcile(self._wanted, assignment_changed=True)
        self.health_interval_s = cfg.health_interval_s
        self._fresh: set[str] = set()  # drones with a new state to answer at the next tick
        self.solve_seconds: Histogram | None = None  # set when metrics are on (edge/metrics.py)

    def _quiet(self, uav: str) -> bool:
        """A drone this replica stands by for and is not ranked first for: its states are only read."""
        return self.assignment.role(uav) is Role.WATCH and self.assignment.order(uav)[0] != self.replica

    def _on_beat(self, key: str, _payload: bytes) -> None:
        """Zenoh's thread: a peer's heartbeat (its name checked when the assignment takes it; our own,
        delivered within our session, are not news)."""
        name = keys.replica_of_token(key)
        if name != self.replica and (name in self._beats_heard or len(self._beats_heard) < MAX_REPLICAS):
            self._beats_heard[name] = self.clock.now_ns()

    def _take_beats(self, now_ns: int) -> None:
        """The beats heard, into the assignment (before any state is judged); ours, when due."""
        self._turned(now_ns)
        for name, heard_ns in dict(self._beats_heard).items():  # a copy: zenoh's thread adds to it
            self.assignment.on_beat(name, heard_ns)

    def _turned(self, now_ns: int) -> None:
        """Our loop runs (also between two answers of a long batch: busy is not hung): the assignment
        notes it (a late turn is a stall of our own, edge/replicas.py), and our heartbeat, when due."""
        stall_ns = self.assignment.on_turn(now_ns, self._turn_gap_ns)
        if stall_ns and self.newest:
            log.info(
                "mpc %s: our loop did not turn for %.0f ms: no peer judged silent for the next %.0f ms",
                self.replica,
                stall_ns / 1e6,
                self.assignment.hold_ns / 1e6,
            )
        if now_ns >= self._next_beat_ns:
            self._next_beat_ns = now_ns + self._beat_period_ns
            self._beat.put_bytes(b"")

    def _mine(self, uav: str) -> bool:
        cfg = self.config.mpc
        return cfg.shard_count == 1 or shard_of(uav, cfg.shard_count) == cfg.shard_index

    def _wanted(self, uav: str) -> bool:
        """Whether to receive the drone's messages: our shard's, and one we fly or stand by for."""
        return self._mine(uav) and self.assignment.mine(uav)

    def _controller(self, uav: str) -> DroneController:
        ctrl = self.controllers.get(uav)
        if ctrl is None:
            ctrl = self.controllers[uav] = DroneController(uav, self.config.mpc, self.config.control)
            self.publishers[uav] = self.bus.publisher(
                keys.downlink(uav, Downlink.COMMAND), Priority.REAL_TIME, express=True
            )
            log.info("mpc: new drone %s (%d served)", uav, len(self.controllers))
        return ctrl

    def handle(self, events: list[Received], now_ns: int) -> None:
        """States and references, oldest first."""
        self.membership.apply()
        self._take_beats(now_ns)
        for item in events:
            message = item.message
            if isinstance(message, Reference):
                self._on_reference(message, item.arrival_ns)
            elif isinstance(message, State):
                self._on_state(item, message, self._fresh)

    def tick(self, now_ns: int) -> float:
        """Answer the fresh states; take over the drones whose holder went silent; drop idle drones."""
        self.membership.apply()
        self._take_beats(now_ns)
        watch = now_ns >= self._next_watch_ns or self.membership.changed
        if watch:
            self._next_watch_ns = now_ns + self._beat_period_ns
            for item in self.feeds.pull():
                assert isinstance(item.message, State)
                self._on_state(item, item.message, self._fresh)
        fresh, self._fresh = self._fresh, set()
        if watch:
            for change in self.assignment.tick(now_ns):
                self.membership.log_change(change)
                fresh.add(change.uav)  # a takeover answers the newest state at once
        for uav in fresh & self.newest.keys():
            if self.assignment.role(uav) is Role.SERVE:
                self._answer(uav, self.newest[uav])
            elif uav not in self.controllers:
                self._controller(uav)  # a standby keeps a controller ready (an OSQP setup is ~1 ms)
            else:
                continue
            self._turned(self.clock.now_ns())
        if watch:
            self._drop_idle()
        self.feeds.reconcile(
            self._wanted, assignment_changed=self.membership.take_changed(), quiet=self._quiet
        )
        # with drones: beating, and often enough to see a holder's lease run out in time
        self._turn_gap_ns = self._beat_period_ns if self.newest else IDLE_TURN_NS
        return self._turn_gap_ns / 1e9

    def _on_reference(self, message: Reference, arrival_ns: int) -> None:
        if self._mine(message.uav) and self.assignment.mine(message.uav):
            self.counters.references += 1
            self._controller(message.uav).reference.update(message, arrival_ns)

    def _on_state(self, item: Received, message: State, fresh: set[str]) -> None:
        uav = message.uav
        if not self._mine(uav):
            self.counters.other_shard += 1
            return
        if not self.assignment.mine(uav):
            self.counters.not_mine += 1
            self.assignment.forget(uav)
            self.newest.pop(uav, None)
            return
        self.counters.states += 1
        term, holder = followed_at(message, self.config.mpc.site)
        self.membership.log_change(self.assignment.on_state(uav, message.seq, term, holder, item.arrival_ns))
        previous = self.newest.get(uav)
        restarted = previous is not None and message.seq < previous.message.seq - 1000
        if previous is None or message.seq > previous.message.seq or restarted:
            if uav in fresh:  # superseded in this batch
                self.counters.stale += 1
            self.newest[uav] = item
            self._copies.pop(uav, None)
            self._paths_heard[uav] = {message.path}
            fresh.add(uav)
        elif message.seq == previous.message.seq and message.path not in (heard := self._paths_heard[uav]):
            if len(heard) < MAX_PATHS:
                heard.add(message.path)
                self._copy(uav, item)
        else:
            self.counters.stale += 1

    def _copy(self, uav: str, item: Received) -> None:
        """Another path's copy of the newest State: answered with its Command, now or once solved."""
        answered = self._answered.get(uav)
        if answered is not None and answered.seq == item.message.seq:
            self._send_copy(uav, answered, item)
        else:
            copies = self._copies.setdefault(uav, [])
            if len(copies) < MAX_PATHS:
                copies.append(item)

    def _send_copy(self, uav: str, command: Command, item: Received) -> None:
        state = item.message
        assert isinstance(state, State)
        hold_ns = max(0, self.clock.now_ns() - item.arrival_ns)
        self.publishers[uav].put(replace(command, state_path=state.path, edge_hold_ns=hold_ns))
        self.counters.copies += 1

    def _answer(self, uav: str, item: Received) -> None:
        ctrl = self._controller(uav)
        state = item.message
        assert isinstance(state, State)
        try:
            plan = ctrl.step(state, item.arrival_ns)
        except SolveError as exc:
            self.counters.solve_failures += 1
            log.warning("mpc: %s seq %d: solve failed (%s); no command sent", uav, state.seq, exc)
            return
        if plan is None:
            self.counters.stale += 1
            return
        self.counters.solve_ms.append(ctrl.problem.last_solve_s * 1000)
        if self.solve_seconds is not None:
            self.solve_seconds.observe(ctrl.problem.last_solve_s)
        if len(self.counters.solve_ms) > 2000:
            del self.counters.solve_ms[:1000]
        command = Command(
            uav=uav,
            seq=state.seq,
            state_seq=plan.state_seq,
            state_stamp_ns=plan.state_stamp_ns,
            edge_hold_ns=max(0, self.clock.now_ns() - item.arrival_ns),
            dt_s=plan.dt_s,
            accel_mps2=plan.accel_mps2,
            yaw_rad=plan.yaw_rad,
            term=self.assignment.term(uav),
            replica=self.replica,
            site=self.config.mpc.site,
            state_path=state.path,
        )
        self.publishers[uav].put(command)
        self.counters.commands += 1
        self._answered[uav] = command
        for copy in self._copies.pop(uav, []):
            if copy.message.seq == state.seq:
                self._send_copy(uav, command, copy)

    def _drop_idle(self) -> None:
        now = self.clock.now_ns()
        timeout_ns = round(self.config.mpc.idle_timeout_s * 1e9)
        for uav in [u for u, item in self.newest.items() if now - item.arrival_ns > timeout_ns]:
            del self.newest[uav]
            self._copies.pop(uav, None)
            self._answered.pop(uav, None)
            self._paths_heard.pop(uav, None)
            self.assignment.forget(uav)
            self.controllers.pop(uav, None)
            publisher = self.publishers.pop(uav, None)
            if publisher is not None:
                publisher.close()
            log.info("mpc: drone %s idle for %.0f s, dropped", uav, self.config.mpc.idle_timeout_s)

    def flying(self) -> int:
        """Drones this replica answers now."""
        return sum(1 for uav in self.newest if self.assignment.role(uav) is Role.SERVE)

    def health(self) -> str:
        c = self.counters
        solve = np.array(c.solve_ms[-500:]) if c.solve_ms else np.zeros(1)
        rejected = self.feeds.rejected()
        a = self.assignment
        return (
            f"{self.membership.health(self.newest, 'flying')} "
            f"stepped_down={a.counters.stepped_down} own_stalls={a.counters.own_stalls} "
            f"tokens_refused={a.counters.members_refused} "
            f"shard={self.config.mpc.shard_index}/{self.config.mpc.shard_count} "
            f"drones={len(self.controllers)} followed={len(self.feeds.subscribed)} "
            f"states={c.states} not_mine={c.not_mine} commands={c.commands} copies={c.copies} "
            f"stale={c.stale} "
            f"rejected={rejected} solve_failures={c.solve_failures} "
            f"references={c.references} queue_drops={self.inbox.dropped} "
            f"solve_ms_p50={np.percentile(solve, 50):.3f} solve_ms_p99={np.percentile(solve, 99):.3f}"
        )


def run(config: Config, *, health_file: Path | None = None) -> int:
    """`dynqos edge mpc` until SIGTERM (edge/service.py's `serve`)."""
    return serve("mpc", config, MpcService, metrics.mpc, health_file=health_file)


def followed_at(state: State, site: str) -> tuple[int, str]:
    """The term and replica the drone follows at `site` ("": the one site, the State's own fields)."""
    if not site:
        return state.command_term, state.command_replica
    return next(((term, replica) for s, term, replica in state.controllers if s == site), (0, ""))
