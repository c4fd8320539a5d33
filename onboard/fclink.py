"""The link to the flight controller (PX4 or the simulator) over MAVLink, through pymavlink.

A reader thread keeps the latest position, velocity and attitude (stamped with our monotonic clock on
arrival), the FC's heartbeat (armed, custom mode) and command acks. Other threads send setpoints and
commands through `send_*`, serialised by a lock. Heartbeat loss is reported, never raised.

What the FC says in STATUSTEXT (PX4's preflight failures, failsafes, refusals) goes to the daemon's
log at the FC's severity, the same text at most once per `TEXT_REPEAT_S`, and the last few are kept for
the reason a failed take-off gives.

The daemon does not rely on the FC's stream configuration: when it first hears the FC (and again
when the FC comes back after a silence) it asks for LOCAL_POSITION_NED and ATTITUDE_QUATERNION at the
rate it needs with MAV_CMD_SET_MESSAGE_INTERVAL, as MAVSDK does. Only messages from the configured
system id are read, so several vehicles can share one ground-station link.

With a signing key every message out is signed (pymavlink) and a message in must be signed with it,
with a timestamp above the last one of its stream; unsigned ones pass only if they are on PX4's list,
or with `accept_unsigned` (common/mavsign.py). Refused messages are counted, never acted on.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common import mavsign
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.errors import TransportError
from dynqos.common.message_base import FC_TEXT_MAX
from dynqos.onboard import px4_events
from dynqos.onboard.fc import FcSaid, FcState
from dynqos.onboard.px4_events import EventCatalogue

log = logging.getLogger(__name__)

PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD = 4, 6
PX4_SUB_LOITER, PX4_SUB_LAND = 3, 6
# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK): a set bit ignores the field.
IGNORE_POSITION = 0b111
IGNORE_VELOCITY = 0b111 << 3
IGNORE_ACCEL = 0b111 << 6
IGNORE_YAW = 1 << 10
IGNORE_YAW_RATE = 1 << 11
ACCEL_AND_YAW_MASK = IGNORE_POSITION | IGNORE_VELOCITY | IGNORE_YAW_RATE  # fly accel, turn to yaw
POSITION_AND_YAW_MASK = IGNORE_VELOCITY | IGNORE_ACCEL | IGNORE_YAW_RATE  # hold position and yaw
STREAM_HZ = 50  # what the daemon asks the FC for: its 50 Hz loop needs a fresh state every tick
STREAMS = (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)
TEXT_REPEAT_S = 10.0  # the same STATUSTEXT is logged again only after this long
TEXTS_KEPT = 8  # the FC's last texts kept for a failure's reason
MAX_TEXTS_TRACKED = 256  # distinct texts whose last logging time is remembered
RESULT_NAMES = {
    0: "accepted",
    1: "temporarily rejected",
    2: "denied",
    3: "unsupported",
    4: "failed",
    5: "in progress",
    6: "cancelled",
}


def severity_level(severity: int) -> int:
    """A MAV_SEVERITY as a logging level: emergency..error are errors, warning a warning, the rest info."""
    if severity <= mavlink.MAV_SEVERITY_ERROR:
        return logging.ERROR
    if severity == mavlink.MAV_SEVERITY_WARNING:
        return logging.WARNING
    return logging.INFO if severity <= mavlink.MAV_SEVERITY_INFO else logging.DEBUG


def result_name(result: int | None) -> str:
    """A MAV_RESULT as words (None: no answer)."""
    if result is None:
        return "no answer"
    return f"{RESULT_NAMES.get(result, 'result')} ({result})"


def serial_device_and_baud(url: str, default_baud: int = 921600) -> tuple[str, int]:
    """`/dev/ttyACM0,921600` (MAVProxy's serial syntax) as (device, baud); other URLs pass through.

    pymavlink takes the baud rate as an argument, not in the URL; a companion computer's serial link
    to PX4 usually runs at 921600 (SER_TEL2_BAUD), not pymavlink's 115200 default.
    """
    device, sep, baud = url.rpartition(",")
    if sep and ":" not in device and baud.isdigit() and int(baud) > 0:
        return device, int(baud)
    return url, default_baud


def use_mavlink2() -> None:
    """MAVLink 2 from the first byte on every link this process opens from now on. pymavlink starts a
    link on MAVLink 1 and, at the first MAVLink 2 packet, swaps in a new parser that has lost the
    signing key (and would accept that very packet unsigned); a signed link cannot start that way."""
    os.environ["MAVLINK20"] = "1"
    mavutil.set_dialect(mavutil.current_dialect)


class FcLink:
    def __init__(
        self,
        url: str,
        *,
        clock: Clock | None = None,
        heartbeat_timeout_s: float = 3.0,
        fc_system_id: int = 1,
        fc_component_id: int = 1,
        fly_yaw: bool = True,
        flow_control: bool = False,
        signing_key: bytes | None = None,
        link_id: int = 1,
        accept_unsigned: bool = False,
        events: EventCatalogue | None = None,
    ) -> None:
        self.url = url
        # Without fly_yaw ([onboard] yaw = "free") the yaw is ignored and the FC keeps its own heading.
        self._yaw_bit = 0 if fly_yaw else IGNORE_YAW
        self.fc_system_id = fc_system_id
        self.fc_component_id = fc_component_id
        self.clock = clock or MonotonicClock()
        self.heartbeat_timeout_ns = round(heartbeat_timeout_s * 1e9)
        device, baud = serial_device_and_baud(url)
        if signing_key is not None:
            use_mavlink2()
            logging.getLogger("pymavlink").setLevel(logging.WARNING)  # not a line per new signed stream
        try:
            self.conn: Any = mavutil.mavlink_connection(
                device,
                baud=baud,
                source_system=1,
                source_component=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER,
                autoreconnect=True,
            )
        except Exception as exc:  # pymavlink raises OSError, ValueError and others for a bad URL
            raise TransportError(f"cannot open MAVLink connection {url!r}: {exc}") from None
        if flow_control and hasattr(self.conn, "set_rtscts"):  # a serial port (docs/onboard.md)
            self.conn.set_rtscts(True)
        self.read_failures = 0  # in a row: a serial device that went away fails every read
        self.signing_on = signing_key is not None
        if signing_key is not None:

            def unsigned_ok(_mav: Any, message_id: int) -> bool:
                return accept_unsigned or mavsign.accepts_unsigned(message_id)

            self.conn.setup_signing(
                signing_key,
                sign_outgoing=True,
                allow_unsigned_callback=unsigned_ok,
                initial_timestamp=mavsign.timestamp_now(),
                link_id=link_id,
            )
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        self.state: FcState | None = None
        self.last_heartbeat_ns: int | None = None
        self.armed = False
        self.custom_mode = 0
        self._acks: dict[int, int] = {}
        self._params: dict[str, float] = {}  # PARAM_VALUE echoes waited for by `set_param`
        self.texts: list[str] = []  # the FC's last STATUSTEXTs, newest last
        self.said: FcSaid | None = None  # the newest of them, with its severity and arrival
        self.texts_heard = 0
        self._text_logged: dict[str, float] = {}
        self.events = events  # PX4's event catalogue, to read its EVENT messages
        self._ack_event = threading.Condition()
        self.setpoints_sent = 0
        self.positions = 0  # LOCAL_POSITION_NED messages read: their rate is what the loop gets
        self.attitudes = 0  # ATTITUDE_QUATERNION messages read: the attitude in each state
        self.lost_reported = False

    # ---- reading ------------------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._read_loop, name="fc-link", daemon=True)
        self._thread.start()

    def _read_loop(self) -> None:
        next_heartbeat = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_heartbeat:
                next_heartbeat = time.monotonic() + 1.0
                self._send(
                    lambda mav: mav.heartbeat_send(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                        mavlink.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        mavlink.MAV_STATE_ACTIVE,
                    )
                )
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.05)
            except Exception as exc:  # a broken datagram, or a serial device gone: never the end
                self._read_failed(exc)
                continue
            if self.read_failures:
                log.info("fc link: reading %s again after %d failed reads", self.url, self.read_failures)
                self.read_failures = 0
            if msg is not None:
                self._handle(msg)

    def _read_failed(self, exc: Exception) -> None:
        """Logged once; from the third failure in a row, read again only every 50 ms (a vanished
        serial device fails at once, every time). The FC's silence is the heartbeat timeout's to report."""
        self.read_failures += 1
        if self.read_failures == 1:
            log.warning("fc link: cannot read %s: %s", self.url, exc)
        if self.read_failures >= 3:
            self._stop.wait(0.05)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        now = self.clock.now_ns()
        if msg.get_srcSystem() != self.fc_system_id:
            return
        if kind == "LOCAL_POSITION_NED":
            self.positions += 1
            values = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if all(math.isfinite(v) for v in values):
                self.state = FcState(now, (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), self._quat)
        elif kind == "ATTITUDE_QUATERNION":
            self.attitudes += 1
            quat = (msg.q1, msg.q2, msg.q3, msg.q4)
            if all(math.isfinite(v) for v in quat):
                self._quat = quat
        elif kind == "HEARTBEAT" and msg.get_srcComponent() == self.fc_component_id:
            first = self.last_heartbeat_ns is None
            self.last_heartbeat_ns = now
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.custom_mode = msg.custom_mode
            if self.lost_reported:
                log.info("fc link: heartbeat is back")
                self.lost_reported = False
                first = True  # it may have rebooted and forgotten the rates we asked for
            if first:
                self._request_streams()
            with self._ack_event:
                self._ack_event.notify_all()  # for `wait_for`
        elif kind in ("STATUSTEXT", px4_events.UNKNOWN_EVENT):
            self._said(msg)
        elif kind in ("COMMAND_ACK", "PARAM_VALUE"):
            self._answer(msg)

    def _answer(self, msg: Any) -> None:
        """A command's ack or a parameter's echo, for whoever waits for it."""
        with self._ack_event:
            if msg.get_type() == "PARAM_VALUE":
                self._params[msg.param_id] = msg.param_value
            else:
                if msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and msg.result != 0:
                    log.warning(
                        "fc link: the flight controller refused a message rate (result %d)", msg.result
                    )
                self._acks[msg.command] = msg.result
            self._ack_event.notify_all()

    def _said(self, msg: Any) -> None:
        """A STATUSTEXT, or PX4's EVENT (pymavlink's dialects do not know it: read from its bytes)."""
        if msg.get_type() == "STATUSTEXT":
            self._fc_says(str(msg.text).strip(), msg.severity)
            return
        event = px4_events.parse_event(bytes(msg.get_msgbuf()))
        if event is not None and event.level < px4_events.LEVEL_DISABLED:
            self._fc_says(px4_events.describe(event, self.events), event.level)

    def _fc_says(self, text: str, severity: int) -> None:
        """A STATUSTEXT or a PX4 event: kept, and logged at its severity unless said just before."""
        if not text:
            return
        self.texts_heard += 1
        self.texts = [*self.texts[-(TEXTS_KEPT - 1) :], text]
        self.said = FcSaid(text[:FC_TEXT_MAX], min(max(int(severity), 0), 7), self.clock.now_ns())
        now = time.monotonic()
        if now - self._text_logged.get(text, -math.inf) >= TEXT_REPEAT_S:
            if len(self._text_logged) >= MAX_TEXTS_TRACKED:
                self._text_logged.clear()
            self._text_logged[text] = now
            log.log(severity_level(severity), "flight controller says: %s", text)

    def _request_streams(self) -> None:
        """Ask for the state at STREAM_HZ; the acks are read (and a refusal logged) by the reader."""
        interval_us = 1_000_000 // STREAM_HZ
        for message_id in STREAMS:
            self._send_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, interval_us)

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Until `predicate` holds, looked at on each heartbeat from the FC (at most `timeout_s`)."""
        with self._ack_event:
            return self._ack_event.wait_for(predicate, timeout=timeout_s)

    def heartbeat_lost(self) -> bool:
        lost = (
            self.last_heartbeat_ns is None
            or self.clock.now_ns() - self.last_heartbeat_ns > self.heartbeat_timeout_ns
        )
        if lost and self.last_heartbeat_ns is not None and not self.lost_reported:
            log.error(
                "fc link: no heartbeat from the flight controller for %.1f s", self.heartbeat_timeout_ns / 1e9
            )
            self.lost_reported = True
        return lost

    def wait_ready(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self._stop.is_set():
            if self.last_heartbeat_ns is not None and self.state is not None:
                return True
            self._stop.wait(0.05)  # polling our own reader's fields; bounded by timeout_s
        return False

    @property
    def offboard(self) -> bool:
        return (self.custom_mode >> 16) & 0xFF == PX4_MAIN_OFFBOARD

    # ---- writing ------------------------------------------------------------------------------------

    def _send(self, action: Any) -> None:
        with self._lock:
            try:
                action(self.conn.mav)
            except OSError as exc:
                log.debug("fc link: send failed: %s", exc)

    def command(
        self, command: int, *params: float, timeout_s: float = 3.0, confirmation: int = 0
    ) -> int | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK result (None on timeout); `confirmation`: 0 for
        the first send, then the number of the retransmission (MAVLink's command protocol)."""
        with self._ack_event:
            self._acks.pop(command, None)
        self._send_command(command, *params, confirmation=confirmation)
        with self._ack_event:
            self._ack_event.wait_for(lambda: command in self._acks, timeout=timeout_s)
            return self._acks.pop(command, None)

    def _send_command(self, command: int, *params: float, confirmation: int = 0) -> None:
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        target = (self.fc_system_id, self.fc_component_id)
        self._send(lambda mav: mav.command_long_send(*target, command, min(confirmation, 255), *p))

    def set_param(self, name: str, value: float, timeout_s: float = 3.0) -> int | None:
        """PARAM_SET of a float parameter; 0 once the FC echoes it with PARAM_VALUE at that value, None
        without an echo in time (an FC that has no such parameter says nothing)."""
        with self._ack_event:
            self._params.pop(name, None)
        target = (self.fc_system_id, self.fc_component_id)
        self._send(
            lambda mav: mav.param_set_send(*target, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)
        )
        with self._ack_event:
            self._ack_event.wait_for(lambda: name in self._params, timeout=timeout_s)
            echoed = self._params.pop(name, None)
        return 0 if echoed is not None and abs(echoed - value) < 1e-3 else None

    def arm(self, confirmation: int = 0) -> int | None:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, confirmation=confirmation)

    def takeoff(self, confirmation: int = 0) -> int | None:
        """MAV_CMD_NAV_TAKEOFF without a position or altitude: PX4 climbs to MIS_TAKEOFF_ALT above home
        (its altitude field is above sea level, which the drone does not need to know)."""
        nan = math.nan
        return self.command(
            mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, nan, nan, nan, nan, confirmation=confirmation
        )

    def set_mode(self, main: int, sub: int = 0, confirmation: int = 0) -> int | None:
        flags = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, flags, main, sub, confirmation=confirmation)

    def land(self) -> int | None:
        return self.command(mavlink.MAV_CMD_NAV_LAND)

    def send_accel(self, accel: tuple[float, float, float], yaw: float) -> None:
        self._send(
            lambda mav: mav.set_position_target_local_ned_send(
                0,
                self.fc_system_id,
                self.fc_component_id,
                mavlink.MAV_FRAME_LOCAL_NED,
                ACCEL_AND_YAW_MASK | self._yaw_bit,
                0,
                0,
                0,
                0,
                0,
                0,
                *accel,
                yaw,
                0.0,
            )
        )
        self.setpoints_sent += 1

    def send_position(self, pos: tuple[float, float, float], yaw: float) -> None:
        self._send(
            lambda mav: mav.set_position_target_local_ned_send(
                0,
                self.fc_system_id,
                self.fc_component_id,
                mavlink.MAV_FRAME_LOCAL_NED,
                POSITION_AND_YAW_MASK | self._yaw_bit,
                *pos,
                0,
                0,
                0,
                0,
                0,
                0,
                yaw,
                0.0,
            )
        )
        self.setpoints_sent += 1

    def signing_counts(self) -> dict[str, int]:
        """Signed messages accepted and refused (a wrong key, a replay, or unsigned) since the start."""
        signing = self.conn.mav.signing
        return {"signed_ok": signing.goodsig_count, "refused": signing.reject_count}

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self.conn.close()
