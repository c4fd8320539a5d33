"""The simulated vehicle on the wire: MAVLink 2 over UDP through pymavlink, like PX4 SITL.

Links, as PX4 SITL has them: the offboard-API link binds 14580 and sends to 14540 (where MAVSDK or
the onboard daemon listens), the ground-station link binds 18570 and sends to 14550 (QGroundControl,
MAVProxy). Once a peer has sent something, replies go to the address it sent from. Telemetry:
HEARTBEAT and SYS_STATUS and EXTENDED_SYS_STATE at 1 Hz, ATTITUDE_QUATERNION and LOCAL_POSITION_NED
at 50 Hz. Datagrams that do not parse are counted and ignored.

Signing, as PX4 does it once a key is provisioned: every message out is signed; a message in must be
signed with the key and carry a timestamp above the last one of its (link, system, component), except
HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and COLLISION (common/mavsign.py). Refused messages are counted
(`unsigned_refused`, `bad_signature`: a wrong key or a replay), never acted on, and never redirect the
replies. Without a key every message is accepted, signed or not, and nothing is signed.

Clocking, as PX4 SITL offers it: real time (scaled by `speed`), or lock-step, where simulated time
advances one telemetry period (20 ms) only after the peer has answered the last telemetry with a
setpoint (as PX4's lock-step waits for actuator outputs). Commands sent before that setpoint act in
the same period. Lock-step runs as fast as the peer can answer and, with a seed, gives the same
flight for the same sequence of messages: what a test wants. With a world, every contact with
an obstacle is logged and counted, so a run that flew through a pillar does not pass unnoticed.
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from dynqos.common import mavsign
from dynqos.sim.vehicle.model import PHYSICS_HZ, STEP_NS, VehicleModel
from dynqos.sim.vehicle.px4 import Mode, Result, Setpoint
from dynqos.sim.vehicle.serial_link import SerialLink
from dynqos.sim.vehicle.world import World, collision

log = logging.getLogger(__name__)

SYSTEM_ID = 1  # instance 0's
COMPONENT_ID = 1
TELEMETRY_HZ = 50
LOCKSTEP_HEARTBEAT_S = 1.0  # in lock-step, repeat the heartbeat in wall time while the peer is silent
STEPS_PER_TELEMETRY = PHYSICS_HZ // TELEMETRY_HZ
# The streams a peer can re-rate with MAV_CMD_SET_MESSAGE_INTERVAL, as PX4 lets it.
STREAMS = (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED)
SUPPORTED_IGNORED_COMMANDS = {
    mavlink.MAV_CMD_REQUEST_MESSAGE,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
}


@dataclass
class Link:
    """One UDP link: a local port we bind and the peer we send to."""

    name: str
    bind: tuple[str, int]
    remote: tuple[str, int]
    sock: socket.socket = field(init=False)
    received: int = 0
    garbage: int = 0
    stream = False  # datagrams: each one holds whole messages

    def open(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(self.bind)
        self.sock.setblocking(False)
        self.bind = self.sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def close(self) -> None:
        self.sock.close()

    def send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):  # nobody listening yet: UDP, like PX4
            self.sock.sendto(data, self.remote)

    def receive(self) -> list[tuple[bytes, tuple[str, int] | None]]:
        """The datagrams waiting, each with its sender."""
        out: list[tuple[bytes, tuple[str, int] | None]] = []
        while True:
            try:
                data, sender = self.sock.recvfrom(65536)
            except OSError:  # BlockingIOError: none left
                return out
            out.append((data, sender))

    def parse(self, data: bytes, signing: Any) -> list[Any]:
        """One datagram's messages, by a parser of its own (garbage in one never spills into the next)."""
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        parser.signing = signing  # the key, and the last timestamp of every peer's stream
        return parser.parse_buffer(data) or []

    def answer(self, sender: tuple[str, int] | None) -> None:
        """Reply where a real MAVLink peer is (called only for a datagram that parsed)."""
        if sender is not None:
            self.remote = sender


class MavlinkVehicle:
    """Steps a VehicleModel in (scaled) real time and speaks MAVLink for it."""

    def __init__(
        self,
        model: VehicleModel,
        links: Sequence[Link | SerialLink],
        *,
        speed: float = 1.0,
        lockstep: bool = False,
        world: World | None = None,
        system_id: int = SYSTEM_ID,
        signing_key: bytes | None = None,
    ) -> None:
        if not speed > 0:
            raise ValueError("speed must be > 0")
        self.model = model
        self.links = list(links)
        self.speed = speed
        self.lockstep = lockstep
        self.world = world
        self.touching: str | None = None
        self._peer_answered = False
        self.system_id = system_id  # PX4 SITL: instance N is system N + 1
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=COMPONENT_ID)
        if signing_key is not None:
            signing = self.mav.signing  # one state for what we send and what we accept (replays)
            signing.secret_key = signing_key
            signing.link_id = 0
            signing.timestamp = mavsign.timestamp_now()
            signing.sign_outgoing = True
            signing.allow_unsigned_callback = lambda _mav, message_id: mavsign.accepts_unsigned(message_id)
        self.signing_on = signing_key is not None
        self._selector = selectors.DefaultSelector()
        self._last_events = 0
        self.stopped = False
        self.stream_steps = dict.fromkeys(STREAMS, STEPS_PER_TELEMETRY)  # message id -> physics steps; 0 off
        self.counters: dict[str, int] = {
            "setpoints": 0,
            "commands": 0,
            "garbage": 0,
            "ignored": 0,
            "collisions": 0,
            "unsigned_refused": 0,
            "bad_signature": 0,
        }

    def open(self) -> None:
        for link in self.links:
            link.open()
            self._selector.register(link.fileno(), selectors.EVENT_READ, link)

    def close(self) -> None:
        self._selector.close()
        for link in self.links:
            link.close()

    # ---- outgoing ----------------------------------------------------------------------------------

    def _send(self, message: Any, link: Link | SerialLink | None = None) -> None:
        data = message.pack(self.mav)
        for target in [link] if link else self.links:
            target.send(data)

    def _time_boot_ms(self) -> int:
        return self.model.now_ns // 1_000_000 & 0xFFFFFFFF

    def heartbeat(self) -> None:
        fc = self.model.fc
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if fc.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink.MAV_STATE_ACTIVE if fc.armed else mavlink.MAV_STATE_STANDBY
        self._send(
            self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, fc.mode.custom_mode, status
            )
        )
        sensors = 0x3FFFFFFF
        self._send(
            self.mav.sys_status_encode(sensors, sensors, sensors, 200, 16200, -1, 90, 0, 0, 0, 0, 0, 0)
        )
        landed = (
            mavlink.MAV_LANDED_STATE_ON_GROUND
            if self.model.plant.on_ground
            else mavlink.MAV_LANDED_STATE_IN_AIR
        )
        if fc.mode is Mode.TAKEOFF:
            landed = mavlink.MAV_LANDED_STATE_TAKEOFF
        elif fc.mode is Mode.LAND and not self.model.plant.on_ground:
            landed = mavlink.MAV_LANDED_STATE_LANDING
        self._send(self.mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, landed))

    def telemetry(self, step: int | None = None) -> None:
        """Attitude and position: each at its own rate at physics step `step`, or both now (None)."""
        s = self.model.state
        t = self._time_boot_ms()

        def due(message_id: int) -> bool:
            every = self.stream_steps[message_id]
            return every > 0 and (step is None or step % every == 0)

        if due(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION):
            w, x, y, z = (float(v) for v in s.quat)
            p, q, r = (float(v) for v in s.rates_rps)
            self._send(self.mav.attitude_quaternion_encode(t, w, x, y, z, p, q, r))
        if due(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
            pos, vel = (float(v) for v in self.model.reported_position()), (float(v) for v in s.vel_mps)
            self._send(self.mav.local_position_ned_encode(t, *pos, *vel))

    def _set_interval(self, message_id: float, interval_us: float) -> Result:
        """MAV_CMD_SET_MESSAGE_INTERVAL as PX4 reads it: -1 stops the stream, 0 restores its default
        rate, a positive interval (microseconds) sets it, rounded to the physics step (200 Hz at most)."""
        if not (math.isfinite(message_id) and math.isfinite(interval_us)) or int(message_id) not in STREAMS:
            return Result.DENIED
        if interval_us < -1:
            return Result.DENIED
        steps = {-1: 0, 0: STEPS_PER_TELEMETRY}.get(int(interval_us))
        if steps is None:
            steps = max(1, round(interval_us * PHYSICS_HZ / 1e6))
        self.stream_steps[int(message_id)] = steps
        return Result.ACCEPTED

    def _ack(self, command: int, result: Result, link: Link | SerialLink) -> None:
        self._send(self.mav.command_ack_encode(command, int(result)), link)

    # ---- incoming ----------------------------------------------------------------------------------

    def poll(self, timeout_s: float) -> None:
        for key, _ in self._selector.select(timeout=max(0.0, timeout_s)):
            link: Link | SerialLink = key.data
            for data, sender in link.receive():
                link.received += 1
                self._handle_datagram(data, link, sender)

    def _handle_datagram(self, data: bytes, link: Link | SerialLink, sender: tuple[str, int] | None) -> None:
        """A datagram (UDP) or the bytes read (serial): whatever messages they complete."""
        try:
            messages = link.parse(data, self.mav.signing)
        except Exception:  # pymavlink raises MAVError and others on garbage; never crash on input
            messages = []
        refused = [m.get_type() == "BAD_DATA" and m.reason == "Invalid signature" for m in messages]
        if any(refused):
            self._refused([m for m, bad in zip(messages, refused, strict=True) if bad], sender)
            messages = [m for m, bad in zip(messages, refused, strict=True) if not bad]
            if not messages:
                return
        # BAD_DATA failed its CRC; UNKNOWN_<id> has an id we cannot CRC-check: both are garbage here.
        good = [m for m in messages if m.get_type() != "BAD_DATA" and not m.get_type().startswith("UNKNOWN")]
        if not good:
            if link.stream and not messages:
                return  # a serial read that completed no message yet: the rest is on its way
            link.garbage += 1
            self.counters["garbage"] += 1
            return
        link.answer(sender)  # answer a real MAVLink peer where it is (garbage never redirects us)
        for message in good:
            try:
                self._handle(message, link)
            except Exception as exc:  # a malformed but parseable message must not stop the vehicle
                self.counters["ignored"] += 1
                log.warning("ignored %s: %s", message.get_type(), exc)

    def _refused(self, refused: list[Any], sender: tuple[str, int] | None) -> None:
        for message in refused:
            kind = "bad_signature" if mavsign.signed_frame(message.data) else "unsigned_refused"
            self.counters[kind] += 1
            if self.counters["unsigned_refused"] + self.counters["bad_signature"] == 1:
                what = "a badly signed or replayed" if kind == "bad_signature" else "an unsigned"
                origin = "the serial link" if sender is None else f"{sender[0]}:{sender[1]}"
                log.warning(
                    "vehicle: signing is on: refused %s message from %s (counted from now on)", what, origin
                )

    def _handle(self, msg: Any, link: Link | SerialLink) -> None:
        kind = msg.get_type()
        fc, state, now = self.model.fc, self.model.state, self.model.now_ns
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            if (
                msg.target_system not in (0, self.system_id)
                or msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED
            ):
                self.counters["ignored"] += 1
                return
            setpoint = Setpoint.from_mavlink(
                msg.type_mask,
                (msg.x, msg.y, msg.z),
                (msg.vx, msg.vy, msg.vz),
                (msg.afx, msg.afy, msg.afz),
                msg.yaw,
            )
            if setpoint is None:
                self.counters["ignored"] += 1
                return
            fc.on_setpoint(setpoint, now)
            self.counters["setpoints"] += 1
            self._peer_answered = True  # lock-step: the controller has answered this period
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            if msg.target_system not in (0, self.system_id):
                return
            self.counters["commands"] += 1
            self._ack(msg.command, self._command(msg), link)
        elif kind == "PARAM_SET":
            if msg.target_system in (0, self.system_id):
                self._param_set(msg.param_id, float(msg.param_value), link)
        elif kind == "SET_MODE":
            if (
                msg.target_system in (0, self.system_id)
                and msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            ):
                main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
                fc.set_mode(main, sub, state, now)
        else:
            self.counters["ignored"] += 1

    def _param_set(self, name: str, value: float, link: Link | SerialLink) -> None:
        """PARAM_SET as PX4 answers it, for the one parameter this vehicle has: MIS_TAKEOFF_ALT, the
        altitude a take-off without one climbs to; echoed with PARAM_VALUE. Any other name: a STATUSTEXT."""
        if name != "MIS_TAKEOFF_ALT" or not (math.isfinite(value) and 0.5 <= value <= 100):
            self.counters["ignored"] += 1
            text = f"[param] {name}: not set".encode()[:50]
            self._send(self.mav.statustext_encode(mavlink.MAV_SEVERITY_WARNING, text), link)
            return
        self.model.fc.default_takeoff_alt_m = value
        self._send(
            self.mav.param_value_encode(name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, 1, 0), link
        )

    def _command(self, msg: Any) -> Result:
        fc, state, now = self.model.fc, self.model.state, self.model.now_ns
        command = msg.command
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if msg.param1 not in (0.0, 1.0):
                return Result.DENIED
            return fc.arm(msg.param1 == 1.0, state, self.model.plant.on_ground, now)
        if command == mavlink.MAV_CMD_NAV_TAKEOFF:
            altitude = float(msg.param7) if math.isfinite(msg.param7) and msg.param7 > 0 else None
            return fc.takeoff(altitude, state, now)
        if command == mavlink.MAV_CMD_NAV_LAND:
            return fc.land(state)
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            if not int(msg.param1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return Result.UNSUPPORTED
            if not (math.isfinite(msg.param2) and math.isfinite(msg.param3)):
                return Result.DENIED
            return fc.set_mode(int(msg.param2), int(msg.param3), state, now)
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(msg.param1, msg.param2)
        if command in SUPPORTED_IGNORED_COMMANDS:
            return Result.ACCEPTED
        return Result.UNSUPPORTED

    # ---- the loop ----------------------------------------------------------------------------------

    def run(self, duration_s: float | None = None, should_stop: Callable[[], bool] | None = None) -> None:
        """Step physics at 200 Hz of simulated time, paced to `speed` x wall time or lock-stepped."""
        if self.lockstep:
            self._run_lockstep(duration_s, should_stop)
            return
        wall_start = time.monotonic()
        sim_start = self.model.now_ns
        while not self.stopped and not (should_stop and should_stop()):
            sim_elapsed_s = (self.model.now_ns - sim_start) / 1e9
            if duration_s is not None and sim_elapsed_s >= duration_s:
                break
            due = wall_start + (sim_elapsed_s + STEP_NS / 1e9) / self.speed
            self.poll(due - time.monotonic())
            if time.monotonic() < due:
                continue
            self._step()

    def _run_lockstep(self, duration_s: float | None, should_stop: Callable[[], bool] | None) -> None:
        sim_start = self.model.now_ns
        self.heartbeat()
        self.telemetry()
        last_heartbeat = time.monotonic()
        while not self.stopped and not (should_stop and should_stop()):
            if duration_s is not None and (self.model.now_ns - sim_start) / 1e9 >= duration_s:
                break
            self.poll(0.05)  # bounded, so that a stop request is seen while the peer is silent
            if not self._peer_answered:
                if time.monotonic() - last_heartbeat >= LOCKSTEP_HEARTBEAT_S:
                    self.heartbeat()  # let a peer that connects late find us
                    self.telemetry()
                    last_heartbeat = time.monotonic()
                continue
            self._peer_answered = False
            for _ in range(STEPS_PER_TELEMETRY):
                self._step()
            last_heartbeat = time.monotonic()

    def _step(self) -> None:
        """One physics step, with telemetry, heartbeat, contact check and event log at their rates."""
        self.model.step()
        step = self.model.now_ns // STEP_NS
        self.telemetry(step)
        if step % STEPS_PER_TELEMETRY == 0:
            self._check_contact()
        if step % PHYSICS_HZ == 1:
            self.heartbeat()
        self._log_events()

    def _check_contact(self) -> None:
        if self.world is None or self.model.plant.on_ground:
            return
        pos = tuple(float(v) for v in self.model.state.pos_m)
        touching = collision(self.world, (pos[0], pos[1], pos[2]))
        if touching and touching != self.touching:
            self.counters["collisions"] += 1
            log.warning(
                "vehicle: collision with %s at (%.2f, %.2f, %.2f) m", touching, pos[0], pos[1], pos[2]
            )
        self.touching = touching

    def _log_events(self) -> None:
        events = self.model.fc.events
        while self._last_events < len(events):
            log.info("vehicle: %s", events[self._last_events])
            self._last_events += 1
        if len(events) > 1000:
            del events[:500]
            self._last_events = len(events)
