"""`dynqos edge mpc`: one process, one controller per drone, discovered from the drones' states.

Zenoh callbacks only decode and queue; one worker thread drains the queue, keeps the newest state
per drone, solves and publishes the Command (REAL_TIME, express). A failed solve sends nothing and
is counted; the drone's watchdog takes over. Idle drones are dropped after `idle_timeout_s`.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from prometheus_client import Histogram

from dynqos.common import keys
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.config import Config
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Command, Reference, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Priority, Publisher, Received
from dynqos.edge import metrics
from dynqos.edge.mpc.controller import DroneController
from dynqos.edge.mpc.problem import SolveError
from dynqos.edge.service import Service, serve

log = logging.getLogger(__name__)


@dataclass
class MpcCounters:
    states: int = 0
    commands: int = 0
    stale: int = 0
    solve_failures: int = 0
    references: int = 0
    other_shard: int = 0
    solve_ms: list[float] = field(default_factory=list)


def shard_of(uav: str, shard_count: int) -> int:
    """The MPC replica that serves `uav`: stable across processes and restarts (unlike hash())."""
    return zlib.crc32(uav.encode()) % shard_count


class MpcService:
    def __init__(self, config: Config, bus: Bus, clock: Clock | None = None) -> None:
        self.config = config
        self.bus = bus
        self.clock = clock or MonotonicClock()
        self.controllers: dict[str, DroneController] = {}
        self.publishers: dict[str, Publisher] = {}
        self.queue: BoundedQueue[Received] = BoundedQueue(4096)
        self.counters = MpcCounters()
        self.state_stats = bus.subscribe(keys.uplink_all_drones(Stream.STATE), self.queue, expect=(State,))
        self.ref_stats = bus.subscribe(
            keys.downlink_all_drones(Downlink.REFERENCE), self.queue, expect=(Reference,)
        )
        self.service = Service("mpc", config.mpc.health_interval_s)
        self.solve_seconds: Histogram | None = None  # set when metrics are on (edge/metrics.py)

    def _mine(self, uav: str) -> bool:
        cfg = self.config.mpc
        return cfg.shard_count == 1 or shard_of(uav, cfg.shard_count) == cfg.shard_index

    def _controller(self, uav: str) -> DroneController:
        ctrl = self.controllers.get(uav)
        if ctrl is None:
            ctrl = self.controllers[uav] = DroneController(uav, self.config.mpc, self.config.control)
            self.publishers[uav] = self.bus.publisher(
                keys.downlink(uav, Downlink.COMMAND), Priority.REAL_TIME, express=True
            )
            log.info("mpc: new drone %s (%d served)", uav, len(self.controllers))
        return ctrl

    def process(self, timeout_s: float = 0.1) -> int:
        """Handle what has arrived; returns how many commands were sent."""
        first = self.queue.get(timeout_s)
        if first is None:
            return 0
        items = [first, *self.queue.drain()]
        newest: dict[str, Received] = {}
        for item in items:
            message = item.message
            if isinstance(message, Reference):
                if not self._mine(message.uav):
                    continue
                self.counters.references += 1
                self._controller(message.uav).reference.update(message, item.arrival_ns)
            elif isinstance(message, State):
                if not self._mine(message.uav):
                    self.counters.other_shard += 1
                    continue
                self.counters.states += 1
                previous = newest.get(message.uav)
                if previous is None or message.seq > previous.message.seq:
                    if previous is not None:
                        self.counters.stale += 1
                    newest[message.uav] = item
                else:
                    self.counters.stale += 1
        sent = 0
        for uav, item in newest.items():
            sent += self._answer(uav, item)
        self._drop_idle()
        return sent

    def _answer(self, uav: str, item: Received) -> int:
        ctrl = self._controller(uav)
        state = item.message
        assert isinstance(state, State)
        try:
            plan = ctrl.step(state, item.arrival_ns)
        except SolveError as exc:
            self.counters.solve_failures += 1
            log.warning("mpc: %s seq %d: solve failed (%s); no command sent", uav, state.seq, exc)
            return 0
        if plan is None:
            self.counters.stale += 1
            return 0
        self.counters.solve_ms.append(ctrl.problem.last_solve_s * 1000)
        if self.solve_seconds is not None:
            self.solve_seconds.observe(ctrl.problem.last_solve_s)
        if len(self.counters.solve_ms) > 2000:
            del self.counters.solve_ms[:1000]
        command = Command(
            uav=uav, seq=state.seq, state_seq=plan.state_seq, state_stamp_ns=plan.state_stamp_ns,
            edge_hold_ns=max(0, self.clock.now_ns() - item.arrival_ns), dt_s=plan.dt_s,
            accel_mps2=plan.accel_mps2, yaw_rad=plan.yaw_rad,
        )  # fmt: skip
        self.publishers[uav].put(command)
        self.counters.commands += 1
        return 1

    def _drop_idle(self) -> None:
        now = self.clock.now_ns()
        timeout_ns = round(self.config.mpc.idle_timeout_s * 1e9)
        for uav in [
            u for u, c in self.controllers.items() if c.last_seen_ns and now - c.last_seen_ns > timeout_ns
        ]:
            del self.controllers[uav]
            self.publishers.pop(uav).close()
            log.info("mpc: drone %s idle for %.0f s, dropped", uav, self.config.mpc.idle_timeout_s)

    def health(self) -> str:
        c = self.counters
        solve = np.array(c.solve_ms[-500:]) if c.solve_ms else np.zeros(1)
        rejected = self.state_stats.rejected + self.ref_stats.rejected
        return (
            f"shard={self.config.mpc.shard_index}/{self.config.mpc.shard_count} "
            f"drones={len(self.controllers)} states={c.states} commands={c.commands} stale={c.stale} "
            f"rejected={rejected} solve_failures={c.solve_failures} "
            f"references={c.references} queue_drops={self.queue.dropped} "
            f"solve_ms_p50={np.percentile(solve, 50):.3f} solve_ms_p99={np.percentile(solve, 99):.3f}"
        )

    def run(self) -> None:
        while not self.service.stop.is_set():
            self.process(0.1)
            self.service.maybe_health(self.health)
        log.info("mpc: stopped; %s", self.health())


def run(config: Config, *, health_file: Path | None = None) -> int:
    """`dynqos edge mpc` until SIGTERM (edge/service.py's `serve`)."""
    return serve("mpc", config, MpcService, metrics.mpc, health_file=health_file)
