"""`dynqos onboard`: the drone's half of the loop, as a thin shell around the onboard core.

The shell only reads and writes. Each 50 Hz tick it reads the flight controller's latest state and
whatever the bus and the camera delivered, calls `OnboardCore.tick`, and writes what comes back: the
setpoint to the FC, the messages to their flow's publisher, the camera's flow and rate, the log lines.
Every decision (commands, supervisor, edge or fallback, FC-silence hold) is the core's
(onboard/core.py); the camera runs on its own thread (onboard/camera_stream.py). Keep it that way:
a decision added here is one the core's tests cannot see.

A drone on two paths (`[[onboard.paths]]`, docs/multipath.md) holds one session per path, all open at
once: every State, status and QoS request goes out on each, the camera on the path the core names, and
what each path delivers is tagged with its name before the core sees it.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import replace

from dynqos.common import keys
from dynqos.common.bus import Bus, Priority, Received
from dynqos.common.camera import CameraSource
from dynqos.common.clock import Clock, MonotonicClock, to_ns
from dynqos.common.config import Config
from dynqos.common.keys import Downlink, Stream
from dynqos.common.lifecycle import ready_line, serving_metrics, stop_on_signals
from dynqos.common.messages import (
    CameraAck,
    Command,
    Detections,
    QosGrant,
    QosMonitoring,
    Reference,
    SupervisorStatus,
)
from dynqos.common.metrics import ProcessMetrics
from dynqos.common.modes import Flow
from dynqos.common.transport import Role, open_bus
from dynqos.onboard.camera_rate import check_installed
from dynqos.onboard.camera_stream import CameraStream, FlowPublishers, PathPublishers
from dynqos.onboard.core import OnboardCore, setpoint_period_ns
from dynqos.onboard.fc import AccelSetpoint, FcState, hold_at
from dynqos.onboard.fclink import PX4_MAIN_AUTO, PX4_SUB_LOITER, FcLink
from dynqos.onboard.links import PathLink, as_carried, path_endpoints
from dynqos.onboard.metrics import DroneMetrics
from dynqos.onboard.modem import modem_poller
from dynqos.onboard.parts import camera_source, fc_link, takeoff_commands
from dynqos.onboard.systemd import SystemdNotifier
from dynqos.onboard.takeoff import Do, ExitAction, TakeoffSequencer, on_exit
from dynqos.onboard.task_runner import TaskRunner, load_tasks
from dynqos.onboard.tick import Outgoing, TickInput, TickOutput
from dynqos.onboard.uplink import Uplink

log = logging.getLogger(__name__)
LAND_WAIT_S = 12.0  # on_exit = "land": how long the daemon waits for the FC to land and disarm

# Each stream's zenoh priority on (the default flow, the priority flow), and whether it may be dropped.
# The status rides above the camera: zenoh serves a link's priorities strictly, so below the camera it
# was starved and dropped whenever the link backed up, which is when a ground station needs it most.
STREAMS = {
    Stream.STATE: (Priority.DATA_HIGH, Priority.REAL_TIME, False),
    Stream.CAMERA_RGB: (Priority.DATA, Priority.INTERACTIVE_LOW, True),
    Stream.CAMERA_DEPTH: (Priority.DATA, Priority.INTERACTIVE_LOW, True),
    Stream.STATUS: (Priority.DATA_HIGH, Priority.INTERACTIVE_LOW, True),
    Stream.QOS: (Priority.DATA_HIGH, Priority.INTERACTIVE_HIGH, False),
}


class OnboardDaemon:
    """The shell: I/O around `OnboardCore`. It holds no state of the flight beyond what it must pass on."""

    def __init__(
        self,
        config: Config,
        *,
        clock: Clock | None = None,
        takeoff: bool | None = None,
        camera: CameraSource | None = None,
    ) -> None:
        """`camera`: the source `[onboard] camera = "sim"` needs (sim/vehicle/camera.py), handed in by the
        starter; the drone's own sources (`files`, `device`) are built here from the config."""
        onboard = config.onboard
        check_installed(onboard.camera_rate_control, onboard.camera_rate_controller)
        self.config = config
        self.sim_camera = camera
        self.cfg = config.onboard
        self.uav = config.drone.id
        self.clock = clock or MonotonicClock()
        self.takeoff_requested = self.cfg.takeoff if takeoff is None else takeoff
        self.stop = threading.Event()
        # the user's tasks ([onboard] tasks): a module that fails to load stops the start in one line
        self.tasks = TaskRunner(self.uav, load_tasks(self.cfg.tasks), self.clock, self.stop)
        self.core = OnboardCore(config, start_ns=self.clock.now_ns(), tasks=self.tasks.tasks)
        self.notifier = SystemdNotifier()
        self.offboard = threading.Event()  # set by the take-off thread once the FC flies offboard
        self.link: FcLink | None = None
        self.bus: Bus | None = None
        self.metrics: DroneMetrics | None = None  # Prometheus, when on (`expose`)
        self.beat: Callable[[str], None] | None = None  # /healthz's record of the health line
        self.camera: CameraStream | None = None
        self.camera_publishers: dict[Stream, PathPublishers] = {}
        self.paths: dict[str, PathLink] = {}  # by name, in configured order
        self.path_sites = {p.name: p.site or p.name for p in self.cfg.paths}  # path -> its router's site
        self.uplink = Uplink(self.stop)  # the tick's publications, put on the wire off the tick thread
        cfg = self.cfg
        self.modem = modem_poller(
            cfg.modem, cfg.modem_url, cfg.modem_command, cfg.modem_interval_s, self.clock.now_ns, self.stop
        )

    # ---- set-up ---------------------------------------------------------------------------------------

    def endpoints(self) -> dict[str, list[str]]:
        return path_endpoints(self.config)

    def open(self, bus: Bus | None = None, *, buses: dict[str, Bus] | None = None) -> None:
        """Open the FC link and one bus per path (`bus`, `buses`: already open, e.g. in-memory ones in a
        test: `bus` for a drone's only path, `buses` by path name)."""
        self.link = fc_link(self.config, self.clock)
        self.link.start()
        for name, endpoints in self.endpoints().items():
            given = (buses or {}).get(name) or (bus if len(self.endpoints()) == 1 else None)
            path_bus = given or open_bus(self.config.zenoh, Role.DRONE, connect=endpoints, clock=self.clock)
            self.paths[name] = self._open_path(name, path_bus)
        self.bus = next(iter(self.paths.values())).bus  # the metrics' session
        for stream in (Stream.CAMERA_RGB, Stream.CAMERA_DEPTH):
            self.camera_publishers[stream] = PathPublishers(
                {name: path.publishers[stream] for name, path in self.paths.items()}
            )
        source = self._camera_source()
        if source is not None:
            self.camera = CameraStream(
                self.uav,
                self.cfg,
                source,
                self.camera_publishers[Stream.CAMERA_RGB],
                self.camera_publishers[Stream.CAMERA_DEPTH],
                pose=self._fc_state,
                clock=self.clock,
                stop=self.stop,
            )
        log.info("onboard %s: flows %s", self.uav, self.endpoints())

    def _open_path(self, name: str, bus: Bus) -> PathLink:
        path = PathLink(name, bus)
        for stream, (on_default, on_priority, drop) in STREAMS.items():
            path.publishers[stream] = FlowPublishers(
                *(
                    bus.publisher(
                        keys.uplink(self.uav, flow, stream),
                        priority,
                        drop_when_congested=drop,
                        express=flow is Flow.PRIORITY and not drop,
                    )
                    for flow, priority in ((Flow.DEFAULT, on_default), (Flow.PRIORITY, on_priority))
                )
            )
        inbox = path.inbox
        routes = [
            (Downlink.COMMAND, inbox.commands, Command),
            (Downlink.CAMERA_ACK, inbox.camera_replies, CameraAck),
            (Downlink.DETECTIONS, inbox.camera_replies, Detections),
            (Downlink.QOS_GRANT, inbox.grants, QosGrant),
            (Downlink.QOS_MONITORING, inbox.grants, QosMonitoring),  # the core's delay reports, if asked
        ]
        if (
            self.cfg.fallback == "continue"
        ):  # the onboard planner continues the mission from the last reference
            routes.append((Downlink.REFERENCE, inbox.references, Reference))
        for kind, queue, expect in routes:
            path.downlink_stats[kind] = bus.subscribe(keys.downlink(self.uav, kind), queue, expect=(expect,))
        self.tasks.open(path)
        # Announced once it listens: the MPC and planner replicas follow only drones that hold this
        # token (edge/feeds.py); the router withdraws it when this session goes. zenoh counts a key's
        # tokens: with two paths the drone stays present while either path holds its token.
        path.presence = bus.declare_token(keys.drone_presence(self.uav))
        return path

    def _camera_source(self) -> CameraSource | None:
        return camera_source(self.config, self.sim_camera)

    def _fc_state(self) -> FcState | None:
        return self.link.state if self.link else None

    # ---- take-off (a procedure with waits, on its own thread) -------------------------------------------

    def take_off(self) -> bool:
        """Arm, take off, enter offboard (onboard/takeoff.py decides each step). Returns False (and logs
        why) if any step is refused or the daemon stops first."""
        link = self.link
        assert link is not None
        sequence = TakeoffSequencer(self.cfg.takeoff_alt_m, self.cfg.fc_timeout_s, self.clock.now_ns())
        commands = takeoff_commands(link, self.cfg.takeoff_alt_m)
        logged = 0
        while not self.stop.is_set():
            heard = link.last_heartbeat_ns is not None
            step = sequence.next(self.clock.now_ns(), link.state, heard, armed=link.armed if heard else None)
            if step.do in commands:
                if step.confirmation:
                    log.warning(
                        "onboard: the flight controller did not answer %s; sending it again (%d)",
                        step.do.value,
                        step.confirmation,
                    )
                sequence.answered(commands[step.do](step.confirmation))
                for refusal in sequence.refusals[logged:]:
                    log.warning("onboard: %s; it said: %s", refusal, " | ".join(link.texts[-3:]) or "nothing")
                logged = len(sequence.refusals)
            elif step.do is Do.HOLD_SETPOINT and step.hold is not None:
                hold = hold_at(step.hold)
                link.send_position(hold.pos_m, hold.yaw_rad)
            elif step.do is Do.FAILED:
                said = " | ".join(link.texts[-3:])
                log.error(
                    "onboard: %s (%s)%s",
                    step.reason,
                    self.cfg.mavlink_url,
                    f"; the flight controller said: {said}" if said else "",
                )
                return False
            elif step.do is Do.DONE and step.hold is not None:
                self.offboard.set()
                log.info("onboard: airborne at %.1f m in offboard mode; offloading", -step.hold.pos_m[2])
                return True
            self.stop.wait(step.wait_s)  # the sequence's own pace: polling the climb, the setpoint rate
        return False

    def _take_off_or_log(self) -> None:
        if not self.take_off():
            log.error("onboard: takeoff failed; staying on the ground, streaming only")

    # ---- the loop -------------------------------------------------------------------------------------

    def tick(self) -> TickOutput:
        """One read-decide-write round."""
        link = self.link
        assert link is not None
        link.heartbeat_lost()  # logs once when the FC goes silent; setpoints keep flowing regardless
        downlink = self._downlink()
        frames = self.camera.sent.drain() if self.camera else []  # after the downlink: see camera_stream
        if self.camera is not None and self.camera.feedback is not None:
            for received in downlink:  # the camera's rate controller reads the edge's arrival reports
                if isinstance(received.message, CameraAck):
                    self.camera.acks.put(received.message)
        space = self.camera.spaciousness.drain() if self.camera else []
        task_sent, task_steers = self.tasks.reports()
        out = self.core.tick(
            TickInput(
                now_ns=self.clock.now_ns(),
                fc=link.state,
                downlink=downlink,
                frames_sent=frames,
                spaciousness_m=space[-1] if space else None,
                offboard=self.offboard.is_set(),
                uplink_bytes=self.uplink_bytes(),
                modem=self.modem.latest if self.modem else None,
                fc_said=link.said,
                task_sent=task_sent,
                task_steers=task_steers,
            )
        )
        self.tasks.hand_out(out.task_jobs, link.state, self.core.offloading)
        for event in out.events:
            log.log(event.level, "%s", event.text)
        if isinstance(out.setpoint, AccelSetpoint):
            link.send_accel(out.setpoint.accel_mps2, out.setpoint.yaw_rad)
        elif out.setpoint is not None:
            link.send_position(out.setpoint.pos_m, out.setpoint.yaw_rad)
        for item in out.publish:
            self._put(item)
            if self.metrics is not None and isinstance(item.message, SupervisorStatus):
                self.metrics.observe(item.message)
        for publishers in self.camera_publishers.values():
            publishers.path = out.camera_path
        if self.camera is not None:
            self.camera.control.flow, self.camera.control.rate_factor = (
                out.camera_flow,
                out.camera_rate_factor,
            )
        return out

    def _put(self, item: Outgoing) -> None:
        """On every path it goes by (the first to arrive is the one that counts), on that path's flow."""
        for name, path in self.paths.items():
            if item.path and item.path != name:
                continue
            message = as_carried(item.message, name, self.path_sites)
            flow = item.flow_on(name)
            self.uplink.put(flow, path.publishers[item.stream].pick(flow), message)

    def _downlink(self) -> list[Received]:
        """What every path delivered since the last tick, by arrival, each item tagged with its path."""
        if len(self.paths) == 1:
            return next(iter(self.paths.values())).inbox.drain()
        items = [replace(item, path=name) for name, path in self.paths.items() for item in path.inbox.drain()]
        return sorted(items, key=lambda item: item.arrival_ns)

    def uplink_bytes(self) -> int:
        """Every byte the drone's publishers handed to zenoh so far, on both flows (the camera thread's
        counts are read without a lock: an int read is atomic, and a tick late is fine for a rate)."""
        return sum(
            p.default.sent_bytes + p.priority.sent_bytes
            for path in self.paths.values()
            for p in path.publishers.values()
        )

    def run(self) -> None:
        """The control loop, until stop is set; then hold (or land) and close."""
        self.uplink.start()
        if self.modem is not None:
            self.modem.start()
        if self.camera is not None:
            self.camera.start()
        self.tasks.start()
        if self.takeoff_requested:
            threading.Thread(target=self._take_off_or_log, name="takeoff", daemon=True).start()
        else:
            log.info(
                "onboard: not taking off (use --takeoff or [onboard] takeoff = true); streaming and waiting"
            )
        self.notifier.notify("READY=1")
        health_ns = to_ns(self.cfg.health_interval_s)
        period_ns = setpoint_period_ns(self.config)
        next_tick = self.clock.now_ns()
        next_health = next_tick + health_ns
        while not self.stop.is_set():
            self.tick()
            now = self.clock.now_ns()
            if now >= next_health:
                next_health = now + health_ns
                self.uplink.report()
                line = self.health()
                log.info("onboard health: %s", line)
                self.notifier.notify(f"STATUS={line}")
                if self.beat is not None:
                    self.beat(line)
            self.notifier.feed_watchdog(now)
            next_tick += period_ns
            delay_ns = next_tick - self.clock.now_ns()
            if delay_ns < -100_000_000:  # fell behind by more than 0.1 s: start afresh, no burst
                next_tick = self.clock.now_ns()
            self.stop.wait(max(0, delay_ns) / 1e9)  # the setpoint rate ([control] setpoint_hz)
        self.notifier.notify("STOPPING=1")
        if self.camera is not None:
            self.camera.join(timeout_s=5)
        self.uplink.join(timeout_s=1)
        self.tasks.join(timeout_s=1)
        self._on_exit()

    def _on_exit(self) -> None:
        link = self.link
        assert link is not None
        action = on_exit(self.core.offloading, self.cfg.on_exit)
        if action is ExitAction.LAND:
            log.info("onboard: stopping: landing (%s)", link.land())
            # PX4 lands and then disarms by itself (COM_DISARM_LAND): the flight ends on the ground
            landed = link.wait_for(lambda: not link.armed, timeout_s=LAND_WAIT_S)
            log.info(
                "onboard: %s", "landed and disarmed" if landed else f"still armed after {LAND_WAIT_S:g} s"
            )
        elif action is ExitAction.HOLD:
            log.info("onboard: stopping: hold position (%s)", link.set_mode(PX4_MAIN_AUTO, PX4_SUB_LOITER))
        log.info("onboard: stopped; %s", self.health())

    def expose(self, metrics: ProcessMetrics) -> None:
        """Feed `metrics` from each published status and the health line (after `open`)."""
        self.metrics = DroneMetrics(self.uav, metrics, self.core.tracker.counters, self.bus)
        self.beat = metrics.health.beat

    def health(self) -> str:
        stats = [s for path in self.paths.values() for s in path.downlink_stats.items()]
        bus_rejected = sum(s.rejected for kind, s in stats if kind is Downlink.COMMAND)
        fields = self.core.health(bus_rejected=bus_rejected)
        fields["bad_downlink"] = sum(s.rejected for _, s in stats)
        fields["uplink_dropped"] = self.uplink.dropped
        fields["fc_setpoints"] = self.link.setpoints_sent if self.link else 0
        fields.update(self.tasks.health())
        if (modem := self.core.modem) is not None:  # the last reading, also when no status gets out
            fields["rsrp_dbm"], fields["sinr_db"] = modem.rsrp_dbm, modem.sinr_db
        if self.camera is not None and (feedback := self.camera.feedback) is not None:
            target = feedback.target_bps
            fields["camera_target_mbps"] = "-" if target is None else f"{target / 1e6:.2f}"
            fields["camera_rate"] = f"{self.camera.rate.factor:.2f}"
            fields["camera_acks_read"], fields["camera_acks_refused"] = (
                feedback.counts.read,
                feedback.counts.refused,
            )
        if self.link is not None and self.link.signing_on:
            counts = self.link.signing_counts()
            fields["fc_signed_ok"], fields["fc_refused"] = counts["signed_ok"], counts["refused"]
        return " ".join(f"{k}={v}" for k, v in fields.items())

    def close(self) -> None:
        for path in self.paths.values():
            path.bus.close()
        if self.link is not None:
            self.link.close()


def run(config: Config, *, takeoff: bool | None = None, camera: CameraSource | None = None) -> int:
    """`dynqos onboard` until SIGTERM, then hold (or land): the FC link and both flows opened, metrics
    served, one ready line. `camera`: the simulator's camera when `[onboard] camera = "sim"`."""
    daemon = OnboardDaemon(config, takeoff=takeoff, camera=camera)
    stop_on_signals("onboard", daemon.stop.set)
    with serving_metrics("onboard", config) as metrics:
        try:
            daemon.open()
            daemon.expose(metrics)
            ready_line("onboard")
            daemon.run()
        finally:
            daemon.close()
    return 0
