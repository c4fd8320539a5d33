"""`dynqos edge planner`: every drone that announces itself and publishes its state gets the mission.

Each drone's mission clock starts when the drone can follow it: at its first state flown offboard
(`State.mode`), not while it stands or takes off, which takes PX4 about 10 s and our vehicle 3, so a
mission is at its start on either. References covering the MPC horizon (and some margin) are published
at `publish_hz` on `dynqos/<uav>/ref`.

Several planners may run, as replicas (edge/replicas.py, docs/reliability.md): one publishes each
drone's references, the other stands by for it, follows its mission time from the references it
hears, and takes over, continuing the mission where it was, when that replica's token goes or it has
sent nothing for `takeover_after_s`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher, Received
from dynqos.common.config import Config, DroneMissionConfig, PlannerConfig
from dynqos.common.keys import Downlink
from dynqos.common.messages import STANDING_BY, MissionRequest, Reference, State
from dynqos.edge import feeds, metrics
from dynqos.edge.feeds import DroneFeeds
from dynqos.edge.membership import Membership, default_replica_id
from dynqos.edge.planner.missions import Mission, load_waypoints, outside_arena
from dynqos.edge.replicas import Assignment, Role
from dynqos.edge.runtime import EdgeCore, Ports, serve

log = logging.getLogger(__name__)


def mission_from_config(cfg: PlannerConfig, uav: str | None = None) -> Mission:
    """The planner's mission, or the one `[planner.drones.<uav>]` gives that drone."""
    m: PlannerConfig | DroneMissionConfig = cfg.drones.get(uav, cfg) if uav is not None else cfg
    waypoints = load_waypoints(m.waypoints_file) if m.mission == "waypoints" else ()
    return Mission(
        kind=m.mission,
        center_m=m.center_m,
        altitude_m=m.altitude_m,
        radius_m=m.radius_m,
        period_s=m.period_s,
        yaw=m.yaw,
        fixed_yaw_rad=m.fixed_yaw_rad,
        lead_in_s=cfg.lead_in_s,
        waypoints=waypoints,
        speed_mps=m.speed_mps,
    )


class PlannerService(EdgeCore):
    name = "planner"

    def __init__(self, config: Config, ports: Ports) -> None:
        bus = ports.bus
        self._init_mission(config, ports)
        self.inbox = ports.inbox
        cfg = self.cfg
        self.assignment = Assignment(
            cfg.replica_id or default_replica_id(),
            lease_ns=round(cfg.takeover_after_s * 1e9),
            holdoff_ns=round(cfg.holdoff_s * 1e9),
            drone_arbitrates=False,
        )
        self.replica = self.assignment.me
        self.membership = Membership("planner", "all", self.assignment, bus)
        self.state_seq: dict[str, int] = {}  # the newest state seen per drone
        # the other replicas' references too: whom they publish for, and their mission time
        self.feeds = DroneFeeds(
            "planner", bus, self.inbox, [feeds.states(), feeds.references(remote_only=True), feeds.missions()]
        )
        self.feeds.reconcile(self.assignment.mine, assignment_changed=True)

    def _init_mission(self, config: Config, ports: Ports) -> None:
        self.config = config
        self.cfg = config.planner
        self.mission = mission_from_config(self.cfg)  # every drone's but those [planner.drones] names
        self.missions = {uav: mission_from_config(self.cfg, uav) for uav in self.cfg.drones}
        self.bus = ports.bus
        self.clock = ports.clock
        self.dt_s = config.control.t_mpc_s
        self.started_ns: dict[str, int] = {}
        self.publishers: dict[str, Publisher] = {}
        # From the wall clock in ms, not 0: a restarted planner (the same replica, the same term) is
        # newer than its last life to every receiver (common/reference.py), at up to 1000 references/s.
        self.seq = time.time_ns() // 1_000_000
        self.sent = 0
        self.mission_seq: dict[str, int] = {}  # the newest MissionRequest seen per drone, flown or refused
        self.missions_flown = 0
        self.missions_refused = 0
        self.health_interval_s = self.cfg.health_interval_s
        self.period_ns = round(1e9 / self.cfg.publish_hz)
        self._next_publish_ns = 0

    def handle(self, events: list[Received], now_ns: int) -> None:
        """New drones, other replicas' references (their mission time), missions from outside."""
        self.membership.apply()
        for item in events:
            message = item.message
            if isinstance(message, State):
                self._on_state(message, item.arrival_ns)
            elif isinstance(message, Reference) and message.uav in self.started_ns:
                seq = self.state_seq.get(message.uav, -1)
                self.membership.log_change(
                    self.assignment.on_command(
                        message.uav, seq, message.term, message.replica, item.arrival_ns
                    )
                )
                if message.replica == self.assignment.seats[message.uav].holder:
                    # follow the mission where the publishing replica has it (to the arrival: ~1 ms)
                    self.started_ns[message.uav] = item.arrival_ns - round(message.mission_t_s * 1e9)
            elif isinstance(message, MissionRequest):
                self._on_mission(message, item.arrival_ns)

    def tick(self, now_ns: int) -> float:
        """At `publish_hz`: who publishes for whom, then each served drone's references."""
        if now_ns < self._next_publish_ns:
            return (self._next_publish_ns - now_ns) / 1e9
        self._next_publish_ns = now_ns + self.period_ns
        self.discover(now_ns)
        self.publish()
        return self.period_ns / 1e9

    def discover(self, now_ns: int) -> None:
        """Replicas that came or went, takeovers due, and the drones to follow for it."""
        self.membership.apply()
        for change in self.assignment.tick(now_ns):
            self.membership.log_change(change)
        self.feeds.reconcile(self.assignment.mine, assignment_changed=self.membership.take_changed())

    def _on_state(self, message: State, arrival_ns: int) -> None:
        uav = message.uav
        if not self.assignment.mine(uav):
            return
        self.state_seq[uav] = message.seq
        self.membership.log_change(self.assignment.on_state(uav, message.seq, 0, "", arrival_ns))
        if uav not in self.started_ns and message.mode != STANDING_BY:
            self.started_ns[uav] = arrival_ns
            self.publishers[uav] = self.bus.publisher(
                keys.downlink(uav, Downlink.REFERENCE), Priority.INTERACTIVE_HIGH
            )
            mission = self.missions.get(uav, self.mission)
            log.info("planner: %s mission (centre %s) starts for %s", mission.kind, mission.center_m, uav)

    def _on_mission(self, request: MissionRequest, arrival_ns: int) -> None:
        """A mission from outside (the ROS 2 bridge), flown from now unless a waypoint is outside the
        arena; each seq once (the bridge re-sends it every second, for replicas that start later: one
        that first hears it then flies it from its first waypoint, where the drone was when asked).
        A drone that cannot follow yet starts it when it can, as any mission."""
        uav = request.uav
        if request.seq <= self.mission_seq.get(uav, -1):
            return
        self.mission_seq[uav] = request.seq
        why = outside_arena(request.waypoints_m, self.cfg.arena_min_m, self.cfg.arena_max_m)
        if why is not None:
            self.missions_refused += 1
            log.warning(
                "planner: refused mission %d for %s from %s, never flown: %s",
                request.seq,
                uav,
                request.source or "?",
                why,
            )
            return
        self.missions[uav] = Mission(
            kind="waypoints",
            waypoints=request.waypoints_m,
            lead_in_s=0.0,
            speed_mps=request.speed_mps or self.cfg.speed_mps,
        )
        if uav in self.started_ns:
            self.started_ns[uav] = arrival_ns
        self.missions_flown += 1
        north, east, down = request.waypoints_m[-1]
        log.info(
            "planner: %s flies mission %d from %s: %d waypoints to (%.2f, %.2f, %.2f) NED",
            uav,
            request.seq,
            request.source or "?",
            len(request.waypoints_m),
            north,
            east,
            down,
        )

    def publish(self) -> None:
        now = self.clock.now_ns()
        for uav, start in self.started_ns.items():
            if self.assignment.role(uav) is not Role.SERVE:
                continue  # standing by: the replica flying it publishes
            t = (now - start) / 1e9
            mission = self.missions.get(uav, self.mission)
            pos, vel, yaw = mission.samples(t, self.dt_s, self.cfg.samples)
            self.seq += 1
            reference = Reference(
                uav=uav,
                seq=self.seq,
                stamp_ns=now,
                dt_s=self.dt_s,
                pos_m=pos,
                vel_mps=vel,
                yaw_rad=yaw,
                mission=mission.kind,
                mission_t_s=max(0.0, t),
                term=self.assignment.term(uav),
                replica=self.replica,
            )
            self.publishers[uav].put(reference)
            self.sent += 1

    def health(self) -> str:
        return (
            f"{self.membership.health(self.started_ns, 'publishing')} "
            f"drones={len(self.started_ns)} references={self.sent} "
            f"followed={len(self.feeds.subscribed)} rejected={self.feeds.rejected()} "
            f"missions={self.missions_flown} refused={self.missions_refused}"
        )


def run(config: Config, *, health_file: Path | None = None) -> int:
    """`dynqos edge planner` until SIGTERM (edge/service.py's `serve`)."""
    return serve("planner", config, PlannerService, metrics.planner, health_file=health_file)
