"""`dynqos onboard`: the drone's half of the loop.

One control loop at the setpoint rate (50 Hz) reads the FC's state, takes in commands and acks,
publishes the State every T_mpc on the flow the supervisor chose, ticks the supervisor, and streams a
setpoint to the FC every tick: the edge's horizon setpoint for now, or the fallback PID's when the
supervisor says so or the command watchdog fires (checked every tick, not only at supervisor ticks).
A camera thread grabs, encodes and publishes RGB-D at the supervisor's rate. For every stream one
publisher per flow is declared up front, so switching flows is choosing the other publisher.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from dynqos.common import keys
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.config import Config
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import (
    LATENCY_LIMIT_MS,
    MAX_STATUS_SAMPLES,
    CameraAck,
    CameraFrame,
    Command,
    Detections,
    Reference,
    State,
)
from dynqos.common.queues import BoundedQueue
from dynqos.common.reference import ReferenceTrack
from dynqos.common.transport import (
    Bus,
    Priority,
    Publisher,
    Received,
    Role,
    default_flow_endpoint,
    open_bus,
    priority_flow_endpoint,
)
from dynqos.onboard.camera import (
    CameraSource,
    DeviceCamera,
    FilesCamera,
    RateController,
    RawFrame,
    SimCamera,
    encode_depth,
    encode_rgb,
)
from dynqos.onboard.commands import CommandTracker
from dynqos.onboard.fclink import PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD, PX4_SUB_LOITER, FcLink, FcState
from dynqos.onboard.monitors import CameraLatencyMonitor
from dynqos.onboard.pacing import FRAME_HEADER_BYTES, Pacer, split
from dynqos.onboard.pid import CascadedPid
from dynqos.onboard.risk import Spaciousness
from dynqos.onboard.supervisor import Decision, Inputs, Supervisor, to_status
from dynqos.sim.world import default_world, load_world

log = logging.getLogger(__name__)

SETPOINT_HZ = 50
STALE_STATE_NS = 500_000_000  # no position from the FC for this long: it is lost, stop using its state


class StatusSamples:
    """The latency samples measured since the last SupervisorStatus (bounded: the newest are kept)."""

    def __init__(self) -> None:
        self._cams: deque[float] = deque(maxlen=MAX_STATUS_SAMPLES)
        self._rtts: deque[float] = deque(maxlen=MAX_STATUS_SAMPLES)

    def extend(self, cams: Iterable[float], rtts: Iterable[float]) -> None:
        self._cams.extend(c for c in cams if 0 <= c <= LATENCY_LIMIT_MS)
        self._rtts.extend(r for r in rtts if 0 <= r <= LATENCY_LIMIT_MS)

    def take(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        out = (tuple(self._cams), tuple(self._rtts))
        self._cams.clear()
        self._rtts.clear()
        return out


@dataclass
class Publishers:
    default: Publisher
    priority: Publisher

    def pick(self, flow: str) -> Publisher:
        return self.priority if flow == "priority" else self.default

    def close(self) -> None:
        self.default.close()
        self.priority.close()


def _yaw(quat: tuple[float, float, float, float]) -> float:
    w, x, y, z = quat
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class SystemdNotifier:
    """sd_notify over $NOTIFY_SOCKET when systemd started us (Type=notify, WatchdogSec).

    Fifteen lines of protocol rather than a dependency: the `sdnotify` package is unmaintained and
    systemd-python needs libsystemd headers on the companion computer. The watchdog is fed from the
    50 Hz control loop at half of $WATCHDOG_USEC, so a stalled loop (not just a dead process) restarts.
    """

    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) if self.address else None
        usec = os.environ.get("WATCHDOG_USEC", "")
        self.watchdog_interval_ns = int(usec) * 1000 // 2 if usec.isdigit() and int(usec) > 0 else None
        self._next_watchdog_ns = 0

    def feed_watchdog(self, now_ns: int) -> None:
        if self.watchdog_interval_ns is not None and now_ns >= self._next_watchdog_ns:
            self._next_watchdog_ns = now_ns + self.watchdog_interval_ns
            self.notify("WATCHDOG=1")

    def notify(self, text: str) -> None:
        if self.sock is not None:
            try:
                self.sock.sendto(text.encode(), self.address)
            except OSError as exc:
                log.debug("sd_notify failed: %s", exc)


class OnboardDaemon:
    def __init__(self, config: Config, *, clock: Clock | None = None, takeoff: bool | None = None) -> None:
        self.config = config
        self.cfg = config.onboard
        self.uav = config.drone.id
        self.clock = clock or MonotonicClock()
        self.takeoff_requested = self.cfg.takeoff if takeoff is None else takeoff
        self.stop = threading.Event()
        self.t_mpc_ns = round(config.control.t_mpc_s * 1e9)
        self.supervisor = Supervisor(config.supervisor, start_ns=self.clock.now_ns())
        self.tracker = CommandTracker(
            self.uav, round(config.supervisor.watchdog_s * 1e9), config.supervisor.window[1]
        )
        self.camera_monitor = CameraLatencyMonitor()
        self.pid = CascadedPid()
        self.rate = RateController(self.cfg.camera_fps)
        pace = self.cfg.camera_pace_mbps
        self.pacer = Pacer(pace * 1e6) if pace > 0 else None
        self.decision: Decision | None = None
        self.flow = "default"
        self.camera_flow = "default"
        self.status_samples = StatusSamples()
        self.control_source = "fallback"
        self.offloading = False  # True once airborne in offboard mode
        self.hold_target: np.ndarray | None = None
        self.hold_yaw = 0.0
        self.last_accel = np.zeros(3)
        self.state_seq = 0
        self.status_seq = 0
        self.spaciousness: float | None = None
        self._space_lock = threading.Lock()
        self.counters = {
            "states": 0,
            "setpoints": 0,
            "fallback_ticks": 0,
            "edge_ticks": 0,
            "frames": 0,
            "camera_bytes": 0,  # encoded image bytes handed to zenoh (headers not counted)
            "switches_to_fallback": 0,
            "detections": 0,
        }
        self.max_setpoint_gap_ms = 0.0
        self.status_gap_ms = 0.0  # the longest setpoint gap since the last status
        self.reference = ReferenceTrack()
        self.notifier = SystemdNotifier()
        self.link: FcLink | None = None
        self.bus: Bus | None = None

    # ---- set-up -------------------------------------------------------------------------------------

    def _endpoints(self) -> list[str]:
        z = self.config.zenoh
        endpoints = []
        for override, build, port in (
            (self.cfg.connect_default, default_flow_endpoint, z.default_port),
            (self.cfg.connect_priority, priority_flow_endpoint, z.priority_port),
        ):
            if override:
                host, _, p = override.rpartition(":")
                endpoints.append(build(z, host=host.strip("[]"), port=int(p)))
            else:
                endpoints.append(build(z, port=port))
        return endpoints

    def open(self) -> None:
        self.link = FcLink(
            self.cfg.mavlink_url, clock=self.clock, heartbeat_timeout_s=self.cfg.heartbeat_timeout_s
        )
        self.link.start()
        self.bus = open_bus(self.config.zenoh, Role.DRONE, connect=self._endpoints(), clock=self.clock)
        bus = self.bus
        # One publisher per stream and flow, declared up front: (default priority, priority-flow priority).
        self.state_pubs = self._pair(Stream.STATE, Priority.DATA_HIGH, Priority.REAL_TIME, drop=False)
        self.rgb_pubs = self._pair(Stream.CAMERA_RGB, Priority.DATA, Priority.INTERACTIVE_LOW, drop=True)
        self.depth_pubs = self._pair(Stream.CAMERA_DEPTH, Priority.DATA, Priority.INTERACTIVE_LOW, drop=True)
        self.status_pubs = self._pair(Stream.STATUS, Priority.DATA_LOW, Priority.INTERACTIVE_LOW, drop=True)
        self.commands: BoundedQueue[Received] = BoundedQueue(256)
        down = {kind: keys.downlink(self.uav, kind) for kind in Downlink}
        self.command_stats = bus.subscribe(down[Downlink.COMMAND], self.commands, expect=(Command,))
        self.acks: BoundedQueue[Received] = BoundedQueue(512)
        self.ack_stats = bus.subscribe(down[Downlink.CAMERA_ACK], self.acks, expect=(CameraAck,))
        self.ack_stats_det = bus.subscribe(down[Downlink.DETECTIONS], self.acks, expect=(Detections,))
        self.downlink_stats = [self.command_stats, self.ack_stats, self.ack_stats_det]
        if (
            self.cfg.fallback == "continue"
        ):  # the onboard planner continues the mission from the last reference
            self.downlink_stats.append(
                bus.subscribe(down[Downlink.REFERENCE], self.acks, expect=(Reference,))
            )
        self.camera = self._camera()
        log.info("onboard %s: flows %s", self.uav, self._endpoints())

    def _pair(self, stream: Stream, on_default: Priority, on_priority: Priority, *, drop: bool) -> Publishers:
        assert self.bus is not None
        express = not drop  # state goes out at once on the priority flow; camera and status are batched

        def declare(flow: Flow, priority: Priority, fast: bool) -> Publisher:
            assert self.bus is not None
            key = keys.uplink(self.uav, flow, stream)
            return self.bus.publisher(key, priority, drop_when_congested=drop, express=fast)

        return Publishers(
            declare(Flow.DEFAULT, on_default, False), declare(Flow.PRIORITY, on_priority, express)
        )

    def _camera(self) -> CameraSource | None:
        cfg = self.cfg
        if cfg.camera == "none" or cfg.camera_fps == 0:
            return None
        if cfg.camera == "sim":
            world = load_world(cfg.world_file) if cfg.world_file else default_world()
            return SimCamera(world, cfg.camera_width, cfg.camera_height, seed=self.config.supervisor.seed)
        if cfg.camera == "files":
            return FilesCamera(cfg.files_dir, cfg.files_intrinsics)
        return DeviceCamera(cfg.device_index, cfg.camera_width, cfg.camera_height, cfg.files_intrinsics)

    # ---- flight ---------------------------------------------------------------------------------------

    def _fc_state(self) -> FcState | None:
        return self.link.state if self.link else None

    def take_off(self) -> bool:
        """Arm, take off, enter offboard. Returns False (and logs why) if any step is refused."""
        link = self.link
        assert link is not None
        if not link.wait_ready(self.cfg.fc_timeout_s):
            log.error(
                "onboard: no heartbeat and position from the flight controller at %s", self.cfg.mavlink_url
            )
            return False
        state = link.state
        assert state is not None
        if link.arm() != 0:
            log.error("onboard: the flight controller refused to arm")
            return False
        if link.takeoff(self.cfg.takeoff_alt_m) != 0:
            log.error("onboard: the flight controller refused to take off")
            return False
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not self.stop.is_set():
            s = link.state
            if s is not None and -s.pos_m[2] >= self.cfg.takeoff_alt_m - 0.15:
                break
            self.stop.wait(0.05)  # polling the vehicle's climb, bounded by 30 s
        s = link.state
        assert s is not None
        self.hold_target = np.array(s.pos_m)
        self.hold_yaw = _yaw(s.quat)
        for _ in range(10):  # PX4 wants a setpoint stream before offboard
            link.send_position(tuple(self.hold_target), self.hold_yaw)
            self.stop.wait(0.02)  # the setpoint stream's own rate
        if link.set_mode(PX4_MAIN_OFFBOARD) != 0:
            log.error("onboard: the flight controller refused offboard mode")
            return False
        self.offloading = True
        self.pid.reset()
        log.info("onboard: airborne at %.1f m in offboard mode; offloading", -s.pos_m[2])
        return True

    # ---- the control loop -----------------------------------------------------------------------------

    def _drain_downlink(self, now: int) -> None:
        for item in self.commands.drain():
            if isinstance(item.message, Command):
                self.tracker.offer(item.message, item.arrival_ns)
        for item in self.acks.drain():
            if isinstance(item.message, CameraAck):
                self.camera_monitor.on_ack(item.message, item.arrival_ns)
            elif isinstance(item.message, Detections):
                self.counters["detections"] += 1
            elif isinstance(item.message, Reference):
                self.reference.update(item.message, item.arrival_ns)

    def _publish_state(self, state: FcState, now: int) -> None:
        self.state_seq += 1
        message = State(
            uav=self.uav,
            seq=self.state_seq,
            stamp_ns=now,
            pos_m=state.pos_m,
            vel_mps=state.vel_mps,
            quat=state.quat,
            rtt_est_ms=self.tracker.rtt_estimate_ms(),
            mode="offboard" if self.offloading else "standby",
        )
        self.tracker.state_sent(self.state_seq, now)
        self.state_pubs.pick(self.flow).put(message)
        self.counters["states"] += 1

    def _supervise(self, now: int) -> None:
        with self._space_lock:
            space, self.spaciousness = self.spaciousness, None
        cams, rtts = self.camera_monitor.take_new(), self.tracker.take_new_rtts()
        self.status_samples.extend(cams, rtts)
        inputs = Inputs(
            camera_latencies_ms=cams,
            cc_rtts_ms=rtts,
            camera_outstanding_ms=self.camera_monitor.oldest_outstanding_ms(now),
            cc_outstanding_ms=self.tracker.oldest_unanswered_ms(now),
            spaciousness_m=space,
            watchdog_expired=self.tracker.watchdog_expired(now),
        )
        decision = self.supervisor.step(inputs, now)
        if decision.transition is not None:
            t = decision.transition
            log.info(
                "supervisor: %s -> %s (%s) P_lat=%s",
                t.source.value,
                t.target.value,
                t.cause,
                "NA" if t.p_lat is None else f"{t.p_lat:.2f}",
            )
        if decision.note:
            log.info("supervisor: %s: %s", decision.state.value, decision.note)
        self.decision = decision
        if self.cfg.qos == "dynamic":
            self.flow = decision.actions.flow
            self.camera_flow = decision.actions.camera
            self.rate.factor = decision.actions.camera_rate_factor
        else:  # static QoS: the supervisor only reports; the watchdog still sends control to the fallback
            self.flow = self.camera_flow = self.cfg.qos

    def _publish_status(self, now: int) -> None:
        if self.decision is None:
            return
        self.status_seq += 1
        last = self.supervisor.log[-1] if self.supervisor.log else None
        status = to_status(
            self.decision, uav=self.uav, seq=self.status_seq, stamp_ns=now, last=last,
            rtt_ms=self.tracker.last_rtt_ms, camera_latency_ms=self.camera_monitor.last_ms,
        )  # fmt: skip
        cams, rtts = self.status_samples.take()
        status = replace(status, setpoint_gap_ms=self.status_gap_ms if self.offloading else None,
                         rtt_samples_ms=rtts, camera_latency_samples_ms=cams)  # fmt: skip
        self.status_gap_ms = 0.0
        if self.cfg.qos != "dynamic":  # report what the drone does, not what the supervisor would do
            status = replace(status, flow=self.flow, camera_flow="", camera_rate_factor=self.rate.factor,
                             control_source=self.control_source)  # fmt: skip
        self.status_pubs.pick(self.flow).put(status)

    def _control(self, state: FcState, now: int) -> None:
        link = self.link
        assert link is not None
        if not self.offloading:
            return
        if now - state.stamp_ns > STALE_STATE_NS:
            # The FC has gone silent: its state is stale, so neither the edge nor the PID can fly on it.
            # Ask it to hold where it was last seen, and keep the stream alive so offboard survives.
            if self.control_source != "fc-lost":
                log.error("onboard: no state from the flight controller for %.1f s: holding position",
                          (now - state.stamp_ns) / 1e9)  # fmt: skip
                self.hold_target = np.array(state.pos_m)
                self.hold_yaw = _yaw(state.quat)
            self.control_source = "fc-lost"
            assert self.hold_target is not None
            hold = self.hold_target
            link.send_position((float(hold[0]), float(hold[1]), float(hold[2])), self.hold_yaw)
            self.counters["setpoints"] += 1
            return
        if self.control_source == "fc-lost":
            log.info("onboard: the flight controller's state is back")
            self.control_source = "holding"
        setpoint = self.tracker.setpoint(now)
        wants_edge = (
            self.cfg.qos != "dynamic"
            or self.decision is None
            or self.decision.actions.control_source == "edge"
        )
        use_edge = wants_edge and setpoint is not None and not self.tracker.watchdog_expired(now)
        if use_edge:
            assert setpoint is not None
            if self.control_source != "edge":
                log.info(
                    "onboard: control from the edge (seq %d)",
                    self.tracker.active.seq if self.tracker.active else -1,
                )
            self.control_source = "edge"
            accel, yaw = np.array(setpoint.accel_mps2), setpoint.yaw_rad
            self.counters["edge_ticks"] += 1
        else:
            if self.control_source != "fallback":
                if self.tracker.watchdog_expired(now):
                    last = self.tracker.last_valid_ns
                    age = "never" if last is None else f"{(now - last) / 1e6:.0f} ms ago"
                    reason = f"watchdog: last valid command {age}"
                else:
                    reason = f"supervisor state {self.decision.state.value if self.decision else '-'}"
                log.warning("onboard: fallback PID holding position (%s)", reason)
                self.counters["switches_to_fallback"] += 1
                self.hold_target = np.array(state.pos_m)
                self.hold_yaw = _yaw(state.quat)
                self.pid.reset(self.last_accel)  # bumpless
            self.control_source = "fallback"
            target, target_vel, yaw = self._fallback_target(now)
            accel = self.pid.step(
                np.array(state.pos_m), np.array(state.vel_mps), target, 1 / SETPOINT_HZ, target_vel
            )
            self.counters["fallback_ticks"] += 1
        self.last_accel = accel
        link.send_accel((float(accel[0]), float(accel[1]), float(accel[2])), yaw)
        self.counters["setpoints"] += 1

    def _fallback_target(self, now: int) -> tuple[np.ndarray, np.ndarray | None, float]:
        """Hold where the fallback took over, or (fallback = continue) follow the last reference while it
        lasts; past its end the reference holds its last sample."""
        assert self.hold_target is not None
        if self.cfg.fallback == "continue":
            window = self.reference.window(now, 1, self.config.control.t_mpc_s)
            if window is not None:
                states, yaws = window
                return states[0, :3], states[0, 3:], float(yaws[0])
        return self.hold_target, None, self.hold_yaw

    def run(self) -> None:
        """The control loop, until stop is set; then hold (or land) and close."""
        assert self.link is not None
        assert self.bus is not None
        camera_thread = threading.Thread(target=self._camera_loop, name="camera", daemon=True)
        camera_thread.start()
        if self.takeoff_requested:
            threading.Thread(target=self._takeoff_then_notify, name="takeoff", daemon=True).start()
        else:
            log.info(
                "onboard: not taking off (use --takeoff or [onboard] takeoff = true); streaming and waiting"
            )
        self.notifier.notify("READY=1")
        period_ns = round(1e9 / SETPOINT_HZ)
        next_tick = self.clock.now_ns()
        next_state = next_tick
        next_status = next_tick
        next_health = next_tick + round(self.cfg.health_interval_s * 1e9)
        last_setpoint_ns: int | None = None
        while not self.stop.is_set():
            now = self.clock.now_ns()
            self._drain_downlink(now)
            state = self._fc_state()
            self.link.heartbeat_lost()  # logs once when the FC goes silent; setpoints keep flowing regardless
            if state is not None and now >= next_state and now - state.stamp_ns <= STALE_STATE_NS:
                next_state += self.t_mpc_ns
                if next_state < now:
                    next_state = now + self.t_mpc_ns
                self._publish_state(state, now)
                self._supervise(now)
            elif self.tracker.watchdog_expired(now) and self.control_source == "edge":
                self._supervise(now)  # the watchdog acts at once, not at the next supervisor tick
            if state is not None:
                sent_before = self.counters["setpoints"]
                self._control(state, now)
                if self.counters["setpoints"] > sent_before:
                    if last_setpoint_ns is not None and self.offloading:
                        gap_ms = (now - last_setpoint_ns) / 1e6
                        self.status_gap_ms = max(self.status_gap_ms, gap_ms)
                        self.max_setpoint_gap_ms = max(self.max_setpoint_gap_ms, gap_ms)
                    last_setpoint_ns = now
            if now >= next_status:
                next_status = now + round(1e9 / self.cfg.status_hz)
                self._publish_status(now)
            if now >= next_health:
                next_health = now + round(self.cfg.health_interval_s * 1e9)
                log.info("onboard health: %s", self.health())
                self.notifier.notify(f"STATUS={self.health()}")
            self.notifier.feed_watchdog(now)
            next_tick += period_ns
            delay = (next_tick - self.clock.now_ns()) / 1e9
            if delay < -0.1:
                next_tick = self.clock.now_ns()
            self.stop.wait(max(0.0, delay))  # the 50 Hz setpoint rate
        self.notifier.notify("STOPPING=1")
        camera_thread.join(timeout=5)
        self._on_exit()

    def _takeoff_then_notify(self) -> None:
        if not self.take_off():
            log.error("onboard: takeoff failed; staying on the ground, streaming only")

    def _on_exit(self) -> None:
        link = self.link
        assert link is not None
        if self.offloading:
            if self.cfg.on_exit == "land":
                log.info("onboard: stopping: landing (%s)", link.land())
            else:
                log.info(
                    "onboard: stopping: hold position (%s)", link.set_mode(PX4_MAIN_AUTO, PX4_SUB_LOITER)
                )
        log.info("onboard: stopped; %s", self.health())

    def health(self) -> str:
        t = self.tracker.counters
        state = self.decision.state.value if self.decision else "-"
        fc_setpoints = self.link.setpoints_sent if self.link else 0
        return (
            f"state={state} flow={self.flow} control={self.control_source} "
            f"rtt_ms={self.tracker.rtt_estimate_ms():.1f} commands_ok={t.accepted} "
            f"rejected={t.rejected + self.command_stats.rejected} (stale={t.stale} unknown={t.unknown_state} "
            f"expired={t.expired} future={t.future} wrong_drone={t.wrong_drone}) "
            f"bad_downlink={sum(s.rejected for s in self.downlink_stats)} "
            + " ".join(f"{k}={v}" for k, v in self.counters.items())
            + f" max_setpoint_gap_ms={self.max_setpoint_gap_ms:.1f} fc_setpoints={fc_setpoints}"
        )

    # ---- the camera -------------------------------------------------------------------------------------

    def _send_frame(
        self,
        pubs: Publishers,
        flow: str,
        seq: int,
        stamp: int,
        raw: RawFrame,
        kind: str,
        encoding: str,
        data: bytes,
    ) -> None:
        h, w = raw.rgb.shape[:2]
        self.camera_monitor.frame_sent(seq, kind, stamp)
        self.counters["camera_bytes"] += len(data)
        parts = [data] if self.pacer is None else split(data, self.cfg.camera_part_bytes)
        for index, part in enumerate(parts):
            if self.pacer is not None:
                wait_ns = self.pacer.reserve(len(part) + FRAME_HEADER_BYTES, self.clock.now_ns())
                if wait_ns > 0 and self.stop.wait(wait_ns / 1e9):
                    return
            frame = CameraFrame(uav=self.uav, seq=seq, stamp_ns=stamp, kind=kind, encoding=encoding, width=w,
                                height=h, intrinsics=raw.intrinsics, payload=part, part=index,
                                parts=len(parts))  # fmt: skip
            pubs.pick(flow).put(frame)

    def _camera_loop(self) -> None:
        if self.camera is None:
            return
        frame_seq = 0
        risk: Spaciousness | None = None
        while not self.stop.is_set():
            now = self.clock.now_ns()
            if not self.rate.due(now):
                self.stop.wait(min(0.1, max(0.001, self.rate.wait_s(now))))  # the camera's frame rate
                continue
            state = self._fc_state()
            raw = self.camera.grab((state.pos_m, state.quat) if state else None)
            if raw is None:
                continue
            frame_seq += 1
            stamp = self.clock.now_ns()
            h, w = raw.rgb.shape[:2]
            flow = self.camera_flow  # one flow for every part of both halves of the frame

            rgb = encode_rgb(raw.rgb, self.cfg.jpeg_quality)
            self._send_frame(self.rgb_pubs, flow, frame_seq, stamp, raw, "rgb", "jpeg", rgb)
            if raw.depth_m is not None:
                depth = encode_depth(raw.depth_m)
                self._send_frame(self.depth_pubs, flow, frame_seq, stamp, raw, "depth", "zstd16", depth)
                if risk is None:
                    risk = Spaciousness(w, h, raw.intrinsics, stride=4)
                value = risk(raw.depth_m)
                if value is not None:
                    with self._space_lock:
                        self.spaciousness = value
            self.counters["frames"] += 1

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
        if self.link is not None:
            self.link.close()
