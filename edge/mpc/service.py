"""`dynqos edge mpc`: one process, one controller per drone, found by the drones' presence tokens.

Zenoh callbacks only decode and queue into the runtime's inbox (edge/runtime.py); the core keeps the
newest state per drone, solves and publishes the Command (REAL_TIME, express) on the runtime's loop.
A failed solve sends nothing and is counted; the drone's watchdog takes over. Idle drones are
dropped after `idle_timeout_s`.

Any number of processes may run side by side: each declares a liveliness token, and edge/replicas.py
decides from the live set which one flies each drone (the next one stands by for it, and takes over
when its token goes or its heartbeat stops for `takeover_after_s`: the beat, sent from the loop every
fifth of that, says the loop still turns). Commands carry the replica's term, which the drone uses to
refuse a replaced one; a standby learns who flies a drone from the drone's own States (the term and
replica it follows), not from the commands, which it does not receive. Nor is each State a Python call
on a standby: the drone's states wait newest-only in zenoh and are read twice a second, and each beat
period once the holder's beats are late (`ALERT_BEATS`), so that when the lease runs out the standby
answers the drone's newest state at once (`[mpc] standby_reads`, docs/reliability.md).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np
from prometheus_client import Histogram

from dynqos.common import keys
from dynqos.common.builtin_tasks import MPC
from dynqos.common.bus import Newest, Priority, Publisher, Received
from dynqos.common.config import Config
from dynqos.common.keys import Downlink
from dynqos.common.messages import Command, Reference, State
from dynqos.common.tasks import Service
from dynqos.edge import feeds, metrics
from dynqos.edge.feeds import DroneFeeds
from dynqos.edge.membership import Membership, default_replica_id
from dynqos.edge.mpc.batch import BatchSolver
from dynqos.edge.mpc.controller import DroneController, Pending, Plan
from dynqos.edge.mpc.counters import MpcCounters
from dynqos.edge.mpc.drones import followed_at, own_after_copy, shard_of
from dynqos.edge.mpc.problem import SolveError
from dynqos.edge.replicas import Assignment, Role
from dynqos.edge.runtime import EdgeCore, Ports

log = logging.getLogger(__name__)

MAX_PATHS = 8  # later copies of one State kept until it is answered (a drone has a few paths)
BEATS_PER_LEASE = 5  # a holder beats five times per lease: four late or lost beats are no takeover;
# a standby watches as often (a takeover is at most a fifth of the lease late: 10 ms at 50 ms)
IDLE_TURN_NS = 100_000_000  # with no drone, the loop turns ten times a second
WATCH_COPY_NS = 500_000_000  # reading copies: the holder copies a drone's State twice a second
# A peer not heard for three beat periods (60% of the lease; polled beats are heard up to a turn late, so
# two came too often on 16 busy cores): the standby reads its drones' states each beat period (reading
# copies: takes them in full, subscribed anew), so it holds the newest when the lease runs out; for at
# least ALERT_HOLD_NS (a loaded peer does not flap them).
ALERT_BEATS = 3
ALERT_HOLD_NS = 300_000_000
TAKEOVER_ANSWERS_LEASES = 4  # a takeover answers the newest state if it came within four leases
PULL_BEATS = 5  # the quiet drones' copies are read once per lease
PULL_STATES_NS = 500_000_000  # reading their own states instead: twice a second (a takeover reads anew)


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
        self._next_pull_ns = 0
        # Replicas of one static shard (or all, unsharded) share its drones among themselves; with sites,
        # within their site only: each site answers every drone (docs/multipath.md).
        group = "all" if cfg.shard_count == 1 else f"shard-{cfg.shard_index}-of-{cfg.shard_count}"
        group = f"site-{cfg.site}-{group}" if cfg.site else group
        self.membership = Membership("mpc", group, self.assignment, bus)
        # The replicas' heartbeats: one newest-only slot in zenoh per live peer, polled on each turn of
        # the loop (a Python call per beat on zenoh's thread made each wait for the GIL behind the solves:
        # eight replicas each took 700 a second, late enough for their peers to take their drones).
        self._group = group
        self._beat_slots: dict[str, Newest] = {}
        self._beat = bus.publisher(
            keys.replica_beat("mpc", group, self.replica), Priority.REAL_TIME, express=True
        )
        self._beat_period_ns = round(cfg.takeover_after_s * 1e9 / BEATS_PER_LEASE)
        self._next_beat_ns = 0
        self._turn_gap_ns = IDLE_TURN_NS  # the longest our loop asked to wait before its next turn
        # Each drone's state and its references (its holder's commands are no standby's business). A
        # drone it stands by for has its states (or the holder's copies of them) kept newest-only in
        # zenoh and read now and then: decoded and queued one by one, they cost a standby most of what
        # serving costs (docs/benchmarks.md, `edge_scale`).
        watch_key = partial(keys.state_watch, "mpc", group)
        quiet_key = watch_key if cfg.standby_reads == "copies" else None  # else the drone's own states
        self.feeds = DroneFeeds(
            "mpc", bus, self.inbox, [feeds.states(pullable=True, quiet_key=quiet_key), feeds.references()]
        )
        self._watch_key = watch_key
        self._reads_copies = quiet_key is not None
        # the holder's copies once per lease (one comes at once when the drone follows another term);
        # the drone's own states twice a second, and each beat period while a peer is late (`_alert`)
        self._pull_period_ns = self._beat_period_ns * PULL_BEATS if quiet_key else PULL_STATES_NS
        self._watch_publishers: dict[str, Publisher] = {}
        self._copy_due_ns: dict[str, int] = {}
        # the term and replica the last copy said the drone follows; late peers, and until when their
        # drones' states come in full
        self._copied: dict[str, tuple[int, str]] = {}
        self._alert_until_ns: dict[str, int] = {}
        self.feeds.reconcile(self._wanted, assignment_changed=True)
        self.health_interval_s = cfg.health_interval_s
        self._fresh: set[str] = set()  # drones with a new state to answer at the next tick
        self.solve_seconds: Histogram | None = None  # set when metrics are on (edge/metrics.py)
        self.solver = BatchSolver(batched=cfg.batch_solves)
        self._window_ns = round(cfg.batch_window_s * 1e9)

    def _quiet(self, uav: str) -> bool:
        """A drone this replica stands by for and is not ranked first for, held by a peer that beats: its
        states (or the holder's copies of them) are read now and then, not each state."""
        a = self.assignment
        if a.role(uav) is not Role.WATCH or (first := a.order(uav)[0]) == self.replica:
            return False
        holder = a.holder(uav)
        holder = first if holder is None else holder
        return holder in a.members and not (self._reads_copies and holder in self._alert_until_ns)

    def _alert(self, now_ns: int) -> bool:
        """The peers whose beats are late by `ALERT_BEATS`: their drones' states read each beat period
        (reading copies: in full) from now until `ALERT_HOLD_NS` after they were last late. Returns
        whether that set changed."""
        late = self.assignment.late_peers(now_ns, ALERT_BEATS * self._beat_period_ns)
        alerted = self._alert_until_ns
        new = late - alerted.keys()
        for peer in new:
            self.counters.alerts += 1
            how = "in full" if self._reads_copies else "read each beat period"
            log.info("mpc %s: replica %s is late: its drones' states %s", self.replica, peer, how)
        for peer in late:
            alerted[peer] = now_ns + ALERT_HOLD_NS
        ended = [p for p, until in alerted.items() if until <= now_ns or p not in self.assignment.members]
        for peer in ended:
            del alerted[peer]
        return bool(new or ended)

    def _read_quiet(self, fresh: set[str], only: Callable[[str], bool] | None = None) -> None:
        """The newest state (or copy) of each drone read from zenoh's slot (`only` some), into `fresh`."""
        for item in self.feeds.pull(only):
            assert isinstance(item.message, State)
            self._on_state(item, item.message, fresh)

    def _held_by_late(self, uav: str) -> bool:
        return self.assignment.holder(uav) in self._alert_until_ns

    def _take_beats(self, now_ns: int) -> None:
        """The peers that beat since the last turn, into the assignment as heard now (before any state
        is judged; later than they came by at most a turn, so a silence is judged late by as much, never
        early); ours, when due. A peer's slot is declared when it joins and closed when it leaves."""
        self._turned(now_ns)
        slots, peers = self._beat_slots, self.assignment.members
        if len(slots) != len(peers) - 1 or not slots.keys() <= peers:
            for peer in peers - slots.keys() - {self.replica}:
                slots[peer] = self.bus.subscribe_newest(keys.replica_beat("mpc", self._group, peer))
            for peer in slots.keys() - peers:
                slots.pop(peer).close()
        for peer, slot in slots.items():
            if slot.poll():
                self.assignment.on_beat(peer, now_ns)

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
        if not watch and (wait_ns := self._gather_ns(now_ns)) > 0:
            self.gathering_s = wait_ns / 1e9  # the runtime takes what arrives meanwhile in one turn
            return self.gathering_s
        self.gathering_s = 0.0
        alerted = False
        if watch:
            self._next_watch_ns = now_ns + self._beat_period_ns
            alerted = self._alert(now_ns)
            if now_ns >= self._next_pull_ns or self.membership.changed:
                self._next_pull_ns = now_ns + self._pull_period_ns
                self._read_quiet(self._fresh)
            elif self._alert_until_ns and not self._reads_copies:  # no subscription to wait for
                self._read_quiet(self._fresh, self._held_by_late)
        fresh, self._fresh = self._fresh, set()
        took: set[str] = set()
        if watch:
            for change in self.assignment.tick(now_ns):
                self.membership.log_change(change)
                took.add(change.uav)  # a takeover answers the newest state at once
            if took and not self._reads_copies:  # whenever its drone's slot was read last
                self._read_quiet(fresh, took.__contains__)
        self._answer_all(fresh, took, now_ns)
        if watch:
            self._drop_idle()
        self.feeds.reconcile(
            self._wanted, assignment_changed=self.membership.take_changed() or alerted, quiet=self._quiet
        )
        # with drones: beating, and often enough to see a holder's lease run out in time
        self._turn_gap_ns = self._beat_period_ns if self.newest else IDLE_TURN_NS
        return self._turn_gap_ns / 1e9

    def _gather_ns(self, now_ns: int) -> int:
        """How much longer the fresh States wait for others, to be solved together: until the batch
        window (`[mpc] batch_window_s`) has passed since the first came, at most a beat period; none
        when every drone with a state is fresh already (a drone alone is answered at once)."""
        fresh = self._fresh
        if not self._window_ns or not fresh or len(fresh) >= len(self.newest):
            return 0
        first = min((item.arrival_ns for uav in fresh if (item := self.newest.get(uav))), default=now_ns)
        return max(0, min(first + self._window_ns - now_ns, self._beat_period_ns))

    def _answerable(self, item: Received, taken: bool, now_ns: int) -> bool:
        """The drone's own state (a holder's copy is answered by no one: the drone's next state is) and,
        on a takeover, one that came within a few leases (not one read before this replica went quiet)."""
        if keys.is_state_watch(item.key):
            return False
        return not taken or now_ns - item.arrival_ns <= TAKEOVER_ANSWERS_LEASES * self.assignment.lease_ns

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
        if (
            previous is None
            or message.seq > previous.message.seq
            or restarted
            or own_after_copy(previous, item)
        ):
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

    def _answer_all(self, fresh: set[str], took: set[str], now_ns: int) -> None:
        """The plans for the drones we fly, solved together (`[mpc] batch_solves`, edge/mpc/batch.py) or
        one by one, each Command sent as soon as its plan is made; a standby readies a controller."""
        pending: list[tuple[Received, DroneController, Pending]] = []
        for uav in (fresh | took) & self.newest.keys():
            item = self.newest[uav]
            if self.assignment.role(uav) is not Role.SERVE or not self._answerable(item, uav in took, now_ns):
                if uav not in self.controllers:
                    self._controller(uav)  # a standby keeps a controller ready (an OSQP setup is ~1 ms)
                    self._turned(self.clock.now_ns())
                continue
            assert isinstance(item.message, State)
            ctrl = self._controller(uav)
            ready = ctrl.prepare(item.message, item.arrival_ns)
            if ready is None:
                self.counters.stale += 1
            else:
                pending.append((item, ctrl, ready))
        if not pending:
            return
        solved = self.solver.solve(
            [ctrl.problem for _, ctrl, _ in pending],
            [ready.x_start for *_, ready in pending],
            [ready.reference for *_, ready in pending],
        )
        if self.solver.product_s is not None:
            self._timed(self.solver.product_s)
        for (item, ctrl, ready), inputs in zip(pending, solved, strict=True):
            if isinstance(inputs, SolveError):
                self.counters.solve_failures += 1
                log.warning(
                    "mpc: %s seq %d: solve failed (%s); no command sent", ctrl.uav, ready.state.seq, inputs
                )
            else:
                self._send(item, ctrl, ctrl.finish(ready, inputs))
            self._turned(self.clock.now_ns())

    def _timed(self, solve_s: float) -> None:
        """A solve's time: one drone's OSQP solve, or a batch's product for all its drones."""
        self.counters.solved(solve_s)
        if self.solve_seconds is not None:
            self.solve_seconds.observe(solve_s)

    def _send(self, item: Received, ctrl: DroneController, plan: Plan) -> None:
        uav, state = ctrl.uav, item.message
        assert isinstance(state, State)
        if ctrl.problem.last_iterations:  # OSQP solved it (a batch's product is timed once)
            self._timed(ctrl.problem.last_solve_s)
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
        self._copy_to_standby(uav, state)
        for copy in self._copies.pop(uav, []):
            if copy.message.seq == state.seq:
                self._send_copy(uav, command, copy)

    def _copy_to_standby(self, uav: str, state: State) -> None:
        """With a peer live (and the group's standbys reading copies: `standby_reads` is one setting for
        all its replicas), the state just answered on the drone's watch key: every `WATCH_COPY_NS`, and
        at once when it says the drone follows another term (the standby must take the next one)."""
        if len(self.assignment.members) < 2 or not self._reads_copies:  # no standby reads them: nothing
            return  # more on the hot path
        now_ns = self.clock.now_ns()
        followed = followed_at(state, self.config.mpc.site)
        if now_ns < self._copy_due_ns.get(uav, 0) and self._copied.get(uav) == followed:
            return
        self._copy_due_ns[uav] = now_ns + WATCH_COPY_NS
        self._copied[uav] = followed
        publisher = self._watch_publishers.get(uav)
        if publisher is None:  # not express: the copies of many drones go in one batch
            publisher = self._watch_publishers[uav] = self.bus.publisher(
                self._watch_key(uav), Priority.DATA_HIGH
            )
        publisher.put(state)
        self.counters.watch_copies += 1

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
            self._copy_due_ns.pop(uav, None)
            self._copied.pop(uav, None)
            for publishers in (self.publishers, self._watch_publishers):
                publisher = publishers.pop(uav, None)
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
            f"stale={c.stale} watch_copies={c.watch_copies} alerts={c.alerts} "
            f"standby_reads={self.config.mpc.standby_reads} "
            f"rejected={rejected} solve_failures={c.solve_failures} "
            f"references={c.references} queue_drops={self.inbox.dropped} "
            f"solve_ms_p50={np.percentile(solve, 50):.3f} solve_ms_p99={np.percentile(solve, 99):.3f}"
            f"{self._batch_health()}"
        )

    def _batch_health(self) -> str:
        b, on = self.solver.counters, "on" if self.solver.batched else "off"
        return (
            f" batch_solves={on} batches={b.batches} exact={b.exact} iterative={b.iterative}"
            f" largest_batch={b.largest}"
        )


def _make(config: Config, ports: Ports, replica: str) -> MpcService:
    if replica:  # --replica-id over [mpc] replica_id
        config = replace(config, mpc=replace(config.mpc, replica_id=replica))
    return MpcService(config, ports)


# `dynqos edge mpc` is `dynqos edge serve dynqos.edge.mpc.service:SERVICE` (edge/tasks.py's `run`).
SERVICE = Service(MPC, make=_make, name="mpc", metrics=metrics.mpc)
