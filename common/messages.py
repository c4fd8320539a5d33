"""Messages between drone and edge (docs/architecture.md) and their msgpack codec.

Every payload is a msgpack map carrying the message type `t`, the schema version `v` and the
fields. `decode` validates every field and raises only DecodeError, whatever bytes arrive, so a
service can count a bad message and go on. Timestamps are the sender's monotonic nanoseconds:
no clock synchronisation is assumed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import msgpack

from dynqos.common import fields as f
from dynqos.common.camera_messages import CameraAck, CameraFrame, Detections
from dynqos.common.errors import DecodeError, MessageError
from dynqos.common.fastdecode import FastDecoder
from dynqos.common.message_base import (
    ACCEL_LIMIT_MPS2,
    ANGLE,
    CAMERA_ENCODINGS,
    CAMERA_KINDS,
    COMMON,
    CONSTRUCTION,
    FC_TEXT_MAX,
    LATENCY_LIMIT_MS,
    LATENCY_MS,
    MAX_DETECTIONS,
    MAX_FRAME_PARTS,
    MAX_HORIZON,
    MAX_MESSAGE_BYTES,
    MAX_MISSION_WAYPOINTS,
    MAX_PAYLOAD_BYTES,
    MAX_REFERENCE_SAMPLES,
    MAX_STATUS_SAMPLES,
    POSITION,
    POSITION_LIMIT_M,
    PROBABILITY,
    RISK_LEVELS,
    RSRP_RANGE_DBM,
    SCHEMA_VERSION,
    SINR_RANGE_DB,
    VELOCITY,
    VELOCITY_LIMIT_MPS,
    M,
    Message,
)
from dynqos.common.modes import ControlSource, Flow, Grant, SupervisorState
from dynqos.common.qos_messages import QosDecision, QosGrant, QosMonitoring, QosRequest
from dynqos.common.task_messages import TaskAnswer, TaskRequest

# The one place every message is imported from: the base's limits, the camera's and the QoS agent's
# messages too.
__all__ = [
    "ACCEL_LIMIT_MPS2",
    "CAMERA_ENCODINGS",
    "CAMERA_KINDS",
    "FC_TEXT_MAX",
    "LATENCY_LIMIT_MS",
    "MAX_DETECTIONS",
    "MAX_FRAME_PARTS",
    "MAX_HORIZON",
    "MAX_MESSAGE_BYTES",
    "MAX_MISSION_WAYPOINTS",
    "MAX_PAYLOAD_BYTES",
    "MAX_REFERENCE_SAMPLES",
    "MAX_STATUS_SAMPLES",
    "MESSAGE_TYPES",
    "POSITION_LIMIT_M",
    "RISK_LEVELS",
    "SCHEMA_VERSION",
    "VELOCITY_LIMIT_MPS",
    "CameraAck",
    "CameraFrame",
    "Command",
    "Detections",
    "Message",
    "MissionRequest",
    "QosDecision",
    "QosGrant",
    "QosMonitoring",
    "QosRequest",
    "Reference",
    "State",
    "SupervisorStatus",
    "TaskAnswer",
    "TaskRequest",
    "decode",
    "decode_as",
    "decode_checked",
    "encode",
]


MAX_SITES = 8  # edge sites a drone may follow at once (State.controllers)
MAX_STATUS_TASKS = 16  # offloaded tasks a status reports ([onboard] tasks holds at most as many)

# State.mode: flown offboard, the drone follows the edge (or its own fallback); standing by, it is on
# the ground or taking off, with nothing to follow yet.
OFFBOARD = "offboard"
STANDING_BY = "standby"


@dataclass(frozen=True, slots=True, kw_only=True)
class State(Message):
    """The drone's state from its flight controller, in local NED."""

    TYPE: ClassVar[str] = "State"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "pos_m": POSITION,
        "vel_mps": VELOCITY,
        "quat": f.vector(4, -1.0001, 1.0001),
        "rtt_est_ms": LATENCY_MS,
        "mode": f.text(32),
        "command_term": f.integer(),
        "command_replica": f.text(64),
        "controllers": f.sequence(f.record(f.text(64), f.integer(), f.text(64)), 0, MAX_SITES),
        "path": f.text(64),
    }

    stamp_ns: int
    pos_m: tuple[float, float, float]
    vel_mps: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    rtt_est_ms: float = 0.0
    mode: str = ""
    # The controller the drone follows now (the term and replica of its last accepted Command), so the
    # edge's replicas agree on who flies it (edge/replicas.py).
    command_term: int = 0
    command_replica: str = ""
    # A drone on two paths follows one controller per edge site (docs/multipath.md): (site, term,
    # replica) for each site it has accepted a Command from; each site's replicas read their own entry.
    controllers: tuple[tuple[str, int, str], ...] = ()
    # The path this copy went by ("" = the drone's only path): a site answers each copy it hears, so
    # the drone times each path's uplink apart (docs/multipath.md).
    path: str = ""

    def _check(self) -> None:
        norm = math.sqrt(sum(q * q for q in self.quat))
        if not 0.9 <= norm <= 1.1:
            raise MessageError("quat", f"not a unit quaternion (norm {norm:.3f})")


@dataclass(frozen=True, slots=True, kw_only=True)
class Command(Message):
    """A short horizon of acceleration setpoints; setpoint k applies at state_stamp_ns + k * dt_s
    on the drone's own clock, so a late command is still usable and no clock sync is needed."""

    TYPE: ClassVar[str] = "Command"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "state_seq": f.integer(),
        "state_stamp_ns": f.integer(),
        "edge_hold_ns": f.integer(),
        "dt_s": f.real(1e-4, 1.0),
        "accel_mps2": f.sequence(f.vector(3, -ACCEL_LIMIT_MPS2, ACCEL_LIMIT_MPS2), 1, MAX_HORIZON),
        "yaw_rad": f.sequence(ANGLE, 1, MAX_HORIZON),
        "term": f.integer(),
        "replica": f.text(64),
        "site": f.text(64),
        "state_path": f.text(64),
    }

    state_seq: int
    state_stamp_ns: int
    edge_hold_ns: int
    dt_s: float
    accel_mps2: tuple[tuple[float, float, float], ...]
    yaw_rad: tuple[float, ...]
    # Fencing (edge/replicas.py): the drone follows only the highest term it has seen; 0 and "" are a
    # controller that does not take part (a single MPC of an older release).
    term: int = 0
    replica: str = ""
    # The edge site whose replicas sent it ("" = one site): terms are compared within a site only, and
    # a drone on two paths takes the first Command for a state from whichever site (docs/multipath.md).
    site: str = ""
    # The path of the State copy it answers (State.path): the first copy is solved, a later copy by
    # another path gets the same Command again under its own path, so each path's uplink is timed.
    state_path: str = ""

    def _check(self) -> None:
        if len(self.yaw_rad) != len(self.accel_mps2):
            raise MessageError(
                "yaw_rad", f"length {len(self.yaw_rad)} differs from accel_mps2 ({len(self.accel_mps2)})"
            )


@dataclass(frozen=True, slots=True, kw_only=True)
class Reference(Message):
    """Trajectory samples from the planner: sample k is due at stamp_ns + k * dt_s (edge clock)."""

    TYPE: ClassVar[str] = "Reference"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "dt_s": f.real(1e-4, 10.0),
        "pos_m": f.sequence(POSITION, 1, MAX_REFERENCE_SAMPLES),
        "vel_mps": f.sequence(VELOCITY, 1, MAX_REFERENCE_SAMPLES),
        "yaw_rad": f.sequence(ANGLE, 1, MAX_REFERENCE_SAMPLES),
        "mission": f.text(64),
        "mission_t_s": f.real(0.0, 1e7),
        "term": f.integer(),
        "replica": f.text(64),
    }

    stamp_ns: int
    dt_s: float
    pos_m: tuple[tuple[float, float, float], ...]
    vel_mps: tuple[tuple[float, float, float], ...]
    yaw_rad: tuple[float, ...]
    mission: str = ""
    # The mission's own time at sample 0, and the planner replica's term and id: a standby planner
    # continues the mission where the one it replaces left it (edge/replicas.py).
    mission_t_s: float = 0.0
    term: int = 0
    replica: str = ""

    def _check(self) -> None:
        n = len(self.pos_m)
        for name in ("vel_mps", "yaw_rad"):
            if len(getattr(self, name)) != n:
                raise MessageError(name, f"must have {n} samples like pos_m")


@dataclass(frozen=True, slots=True, kw_only=True)
class MissionRequest(Message):
    """A mission for one drone from outside the edge, to its planner replicas: fly these waypoints
    (local NED; the first is where the drone was when it was asked) and hold the last. `dynqos edge
    ros2` sends one for a ROS 2 node's Path or goal, and re-sends it with the same seq every second
    until another replaces it, so a planner replica that starts later flies it too; a planner applies
    a seq once, and refuses one outside its arena (docs/ros2.md)."""

    TYPE: ClassVar[str] = "MissionRequest"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "waypoints_m": f.sequence(POSITION, 2, MAX_MISSION_WAYPOINTS),
        "speed_mps": f.real(0.0, 50.0),
        "source": f.text(64),
    }

    stamp_ns: int
    waypoints_m: tuple[tuple[float, float, float], ...]
    speed_mps: float = 0.0  # 0: the planner's own [planner] speed_mps
    source: str = ""  # who asked, for the logs (e.g. "ros2:/dynqos/uav1/mission")


@dataclass(frozen=True, slots=True, kw_only=True)
class SupervisorStatus(Message):
    """What the supervisor decided this tick and why. Before any sample a latency or risk signal is
    "NA" and its estimate None; a probability is then 0.0 and means nothing."""

    TYPE: ClassVar[str] = "SupervisorStatus"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "state": f.member(SupervisorState),
        "flow": f.member(Flow),
        "camera_rate_factor": f.real(0.0, 1.0),
        "control_source": f.member(ControlSource),
        "latency": f.choice(("LL", "HL", "NA")),
        "risk": f.choice(("LR", "MR", "HR", "NA")),
        "watchdog": f.boolean,
        "t_cam_ms": f.optional(LATENCY_MS),
        "t_cc_ms": f.optional(LATENCY_MS),
        "spaciousness_m": f.optional(f.real(0.0, 1e6)),
        "depth_lost": f.boolean,
        "p_cam": PROBABILITY,
        "p_cc": PROBABILITY,
        "p_lat": PROBABILITY,
        "p_cs": PROBABILITY,
        "prev_state": f.member(SupervisorState),
        "cause": f.text(200),
        "changed_ns": f.integer(),
        "rtt_ms": f.optional(LATENCY_MS),
        "camera_latency_ms": f.optional(LATENCY_MS),
        "setpoint_gap_ms": f.optional(LATENCY_MS),
        "camera_flow": f.member(Flow),
        "fallbacks": f.integer(),
        "fallback_s": f.real(0.0, 1e9),
        "control_changed_ns": f.integer(),
        "command_age_ms": f.optional(LATENCY_MS),
        "camera_bytes": f.integer(),
        "uplink_bytes": f.integer(),
        "qos_grant": f.member(Grant),
        "qos_agent": f.boolean,
        "rtt_samples_ms": f.sequence(LATENCY_MS, 0, MAX_STATUS_SAMPLES),
        "camera_latency_samples_ms": f.sequence(LATENCY_MS, 0, MAX_STATUS_SAMPLES),
        "rsrp_dbm": f.optional(f.real(*RSRP_RANGE_DBM)),
        "sinr_db": f.optional(f.real(*SINR_RANGE_DB)),
        "fc_text": f.text(FC_TEXT_MAX),
        "fc_severity": f.optional(f.integer(0, 7)),
        "path_rtt_samples_ms": f.sequence(
            f.record(f.text(64), f.sequence(LATENCY_MS, 0, MAX_STATUS_SAMPLES)), 0, MAX_SITES
        ),
        "camera_path": f.text(64),
        "duplicates": f.integer(),
        "site": f.text(64),
        "site_wins": f.sequence(f.record(f.text(64), f.integer()), 0, MAX_SITES),
        "path_states": f.sequence(
            f.record(f.text(64), f.member(SupervisorState), f.member(Flow)), 0, MAX_SITES
        ),
        "tasks": f.sequence(
            f.record(
                f.text(32),
                f.choice(("edge", "fallback")),
                f.integer(),
                f.integer(),
                f.integer(),
                f.real(0.0, 1e9),
                f.sequence(LATENCY_MS, 0, MAX_STATUS_SAMPLES),
            ),
            0,
            MAX_STATUS_TASKS,
        ),
    }

    stamp_ns: int
    state: SupervisorState
    flow: Flow  # the state's flow
    camera_rate_factor: float
    control_source: ControlSource  # who flies the drone now (what it does, not what it was asked)
    camera_flow: Flow  # the camera's flow (it differs from `flow` while the camera probes the default flow)
    latency: str
    risk: str
    watchdog: bool
    t_cam_ms: float | None
    t_cc_ms: float | None
    spaciousness_m: float | None
    p_cam: float
    p_cc: float
    p_lat: float
    p_cs: float
    prev_state: SupervisorState
    cause: str
    changed_ns: int
    rtt_ms: float | None = None  # the latest C&C RTT sample, for plots
    camera_latency_ms: float | None = None  # the latest camera latency sample
    setpoint_gap_ms: float | None = None  # longest pause between setpoints to the FC since the last status
    rtt_samples_ms: tuple[float, ...] = ()  # every C&C RTT measured since the last status, for statistics
    camera_latency_samples_ms: tuple[float, ...] = ()  # every camera latency since the last status
    fallbacks: int = 0  # hand-overs to the fallback PID since the daemon started
    # seconds the fallback PID flew since then, counted by the drone: right even when statuses were
    # lost meanwhile (a site or router down), where time between statuses is not
    fallback_s: float = 0.0
    control_changed_ns: int = 0  # when control_source last changed (onboard clock; 0: never)
    command_age_ms: float | None = None  # age of the last valid command at that change (None: none yet)
    camera_bytes: int = 0  # camera bytes handed to zenoh since the daemon started, before any drop
    uplink_bytes: int = 0  # every uplink message's bytes handed to zenoh since then (camera included)
    qos_grant: Grant = Grant.NONE  # what the network grants the priority flow (the agent's last word)
    qos_agent: bool = False  # a QoS agent answered recently (False: links only, no network request)
    depth_lost: bool = False  # depth stopped for risk_stale_s: risk is NA and read as HR
    rsrp_dbm: float | None = None  # what the drone's modem reports lately (None: no modem, or no reading)
    sinr_db: float | None = None
    # what the flight controller said last (STATUSTEXT, or a PX4 event), while it is recent, and its
    # MAV_SEVERITY (0 emergency .. 7 debug): "" and None when it said nothing lately
    fc_text: str = ""
    fc_severity: int | None = None
    # A drone on two paths (docs/multipath.md): each path's command RTTs since the last status (the
    # first answer to each State copy it carried: its uplink), the camera's path, the duplicate
    # Commands dropped since the daemon started, the site whose Command flies the drone now, and how
    # many Commands each site won (applied) since the daemon started. Empty with one path.
    path_rtt_samples_ms: tuple[tuple[str, tuple[float, ...]], ...] = ()
    camera_path: str = ""
    duplicates: int = 0
    site: str = ""
    site_wins: tuple[tuple[str, int], ...] = ()
    # each path's own PFSM: its state and the flow its traffic takes (docs/supervisor.md, "Two paths")
    path_states: tuple[tuple[str, SupervisorState, Flow], ...] = ()
    # the user's offloaded tasks (docs/offload.md): each one's name, whether the edge's answer or its
    # fallback applies, its requests, answers applied and misses since the daemon started, the seconds
    # its fallback flew, and its round trips since the last status
    tasks: tuple[tuple[str, str, int, int, int, float, tuple[float, ...]], ...] = ()


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        State,
        Command,
        CameraFrame,
        CameraAck,
        Detections,
        Reference,
        SupervisorStatus,
        QosRequest,
        MissionRequest,
        QosGrant,
        QosDecision,
        QosMonitoring,
        TaskRequest,
        TaskAnswer,
    )
}


_FIELD_NAMES = {cls: tuple(field.name for field in fields(cls)) for cls in MESSAGE_TYPES.values()}
_FAST = FastDecoder(MESSAGE_TYPES, SCHEMA_VERSION)
CONSTRUCTION.fast = _FAST


def encode(message: Message) -> bytes:
    body: dict[str, Any] = {"t": message.TYPE, "v": SCHEMA_VERSION}
    for name in _FIELD_NAMES[type(message)]:
        body[name] = getattr(message, name)
    packed: bytes = msgpack.packb(body, use_bin_type=True)
    return packed


def _unpack(data: Any) -> Any:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise DecodeError("<payload>", f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_MESSAGE_BYTES:
        raise DecodeError("<payload>", f"{len(data)} bytes exceed the limit of {MAX_MESSAGE_BYTES}")
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_bin_len=MAX_PAYLOAD_BYTES,
            max_str_len=4096,
            max_array_len=4096,
            max_map_len=64,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises many types (ExtraData, FormatError, ValueError, ...)
        raise DecodeError("<payload>", f"not valid msgpack ({type(exc).__name__}: {exc})"[:200]) from None


def decode(data: Any) -> Message:
    """Bytes -> a validated message. Raises DecodeError naming the field, and nothing else. Valid
    messages are decoded in C (common/fastdecode.py); the rest by `decode_checked`, which names why."""
    if isinstance(data, (bytes, bytearray, memoryview)) and len(data) <= MAX_MESSAGE_BYTES:
        message: Message | None = _FAST.decode(data)
        if message is not None:
            return message
    return decode_checked(data)


def decode_checked(data: Any) -> Message:
    """The reference decoder: msgpack, then every field's validator in Python."""
    body = _unpack(data)
    if not isinstance(body, dict):
        raise DecodeError("<payload>", f"expected a map, got {type(body).__name__}")
    type_name = body.pop("t", None)
    cls = MESSAGE_TYPES.get(type_name) if isinstance(type_name, str) else None
    if cls is None:
        raise DecodeError("t", f"unknown message type {str(type_name)[:40]!r}")
    version = body.pop("v", None)
    if version != SCHEMA_VERSION or isinstance(version, bool):
        raise DecodeError(
            "v", f"schema version {str(version)[:20]!r} is not supported (expected {SCHEMA_VERSION})"
        )
    expected = set(_FIELD_NAMES[cls])
    for name in body:
        if name not in expected:
            raise DecodeError(name, f"unknown field in {cls.TYPE}")
    try:
        return cls(**body)
    except MessageError as exc:
        raise DecodeError(exc.field, exc.reason) from None
    except TypeError as exc:  # a required field is missing
        missing = sorted(expected - set(body))
        raise DecodeError(missing[0] if missing else "<message>", f"missing in {cls.TYPE} ({exc})") from None
    except Exception as exc:  # last line of defence: the contract is DecodeError only
        raise DecodeError("<message>", f"{type(exc).__name__}: {exc}"[:200]) from None


def decode_as(data: Any, cls: type[M]) -> M:
    message = decode(data)
    if not isinstance(message, cls):
        raise DecodeError("t", f"expected {cls.TYPE}, got {message.TYPE}")
    return message
