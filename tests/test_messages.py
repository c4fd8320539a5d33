from __future__ import annotations

import contextlib
import math
from dataclasses import fields, replace
from typing import Any

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynqos.common import keys
from dynqos.common import messages as m
from dynqos.common.errors import DecodeError, MessageError
from dynqos.common.modes import ControlSource, Flow, Grant, SupervisorState
from tests.statuses import status

uav_ids = st.from_regex(keys.UAV_ID_PATTERN, fullmatch=True)
u63 = st.integers(0, 2**63 - 1)


def reals(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False)


def vec(n: int, lo: float, hi: float) -> st.SearchStrategy[tuple[float, ...]]:
    return st.tuples(*[reals(lo, hi)] * n)


unit_quats = (
    vec(4, -1.0, 1.0)
    .filter(lambda q: sum(x * x for x in q) > 0.01)
    .map(lambda q: tuple(x / math.sqrt(sum(y * y for y in q)) for x in q))
)


@st.composite
def commands(draw: st.DrawFn) -> m.Command:
    k = draw(st.integers(1, m.MAX_HORIZON))
    return m.Command(
        uav=draw(uav_ids),
        seq=draw(u63),
        state_seq=draw(u63),
        state_stamp_ns=draw(u63),
        edge_hold_ns=draw(u63),
        dt_s=draw(reals(1e-4, 1.0)),
        accel_mps2=draw(st.lists(vec(3, -100, 100), min_size=k, max_size=k)),
        yaw_rad=draw(st.lists(reals(-100, 100), min_size=k, max_size=k)),
    )


@st.composite
def references(draw: st.DrawFn) -> m.Reference:
    k = draw(st.integers(1, 50))
    return m.Reference(
        uav=draw(uav_ids),
        seq=draw(u63),
        stamp_ns=draw(u63),
        dt_s=draw(reals(1e-4, 10)),
        pos_m=draw(st.lists(vec(3, -1e5, 1e5), min_size=k, max_size=k)),
        vel_mps=draw(st.lists(vec(3, -1e3, 1e3), min_size=k, max_size=k)),
        yaw_rad=draw(st.lists(reals(-100, 100), min_size=k, max_size=k)),
        mission=draw(st.text(max_size=64)),
    )


@st.composite
def detections(draw: st.DrawFn) -> m.Detections:
    n = draw(st.integers(0, 10))
    return m.Detections(
        uav=draw(uav_ids),
        seq=draw(u63),
        frame_seq=draw(u63),
        stamp_ns=draw(u63),
        circles_px=draw(st.lists(vec(3, -1e5, 1e5), min_size=n, max_size=n)),
        centers_m=draw(st.lists(st.none() | vec(4, -1e5, 1e5), min_size=n, max_size=n)),
    )


states = st.builds(
    m.State,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    pos_m=vec(3, -1e5, 1e5),
    vel_mps=vec(3, -1e3, 1e3),
    quat=unit_quats,
    rtt_est_ms=reals(0, 1e7),
    mode=st.text(max_size=32),
)
frames = st.builds(
    m.CameraFrame,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    kind=st.sampled_from(m.CAMERA_KINDS),
    encoding=st.sampled_from(m.CAMERA_ENCODINGS),
    width=st.integers(1, 8192),
    height=st.integers(1, 8192),
    intrinsics=st.tuples(reals(1e-3, 1e6), reals(1e-3, 1e6), reals(0, 1e6), reals(0, 1e6)),
    payload=st.binary(max_size=2048),
    depth_unit_m=reals(1e-6, 1.0),
)
acks = st.builds(
    m.CameraAck,
    uav=uav_ids,
    seq=u63,
    frame_seq=u63,
    kind=st.sampled_from(m.CAMERA_KINDS),
    stamp_ns=u63,
    edge_hold_ns=u63,
)
statuses = st.builds(
    m.SupervisorStatus,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    state=st.sampled_from(SupervisorState),
    flow=st.sampled_from(Flow),
    camera_flow=st.sampled_from(Flow),
    camera_rate_factor=reals(0, 1),
    control_source=st.sampled_from(ControlSource),
    latency=st.sampled_from(["LL", "HL", "NA"]),
    risk=st.sampled_from(["LR", "MR", "HR", "NA"]),
    watchdog=st.booleans(),
    t_cam_ms=st.none() | reals(0, 1e7),
    t_cc_ms=st.none() | reals(0, 1e7),
    spaciousness_m=st.none() | reals(0, 1e6),
    p_cam=reals(0, 1),
    p_cc=reals(0, 1),
    p_lat=reals(0, 1),
    p_cs=reals(0, 1),
    prev_state=st.sampled_from(SupervisorState),
    cause=st.text(max_size=200),
    changed_ns=u63,
    fallbacks=u63,
    control_changed_ns=u63,
    command_age_ms=st.none() | reals(0, 1e7),
    camera_bytes=u63,
    uplink_bytes=u63,
    qos_grant=st.sampled_from(Grant),
    qos_agent=st.booleans(),
)
risks = st.sampled_from(m.RISK_LEVELS)
qos_requests = st.builds(
    m.QosRequest,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    want=st.booleans(),
    risk=risks,
    latency_excess=reals(-1, 1),
    offered_mbps=reals(0, 1e5),
)
qos_decisions = st.builds(
    m.QosDecision,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    action=st.sampled_from(["grant", "deny", "revoke", "release"]),
    reason=st.text(max_size=500),
    risk=risks,
    latency_excess=reals(-1, 1),
    holders=st.lists(uav_ids, max_size=8).map(tuple),
)
qos_grants = st.builds(
    m.QosGrant,
    uav=uav_ids,
    seq=u63,
    grant=st.sampled_from(Grant),
    backend=st.sampled_from(["links", "camara", "nef"]),
    session_id=st.text(max_size=64),
    reason=st.text(max_size=300),
    answers_seq=u63,
)
qos_monitorings = st.builds(
    m.QosMonitoring,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    subscription_id=st.text(max_size=64),
    uplink_ms=st.none() | reals(0, 1e6),
    downlink_ms=st.none() | reals(0, 1e6),
    round_trip_ms=st.none() | reals(0, 1e6),
    period_s=st.integers(1, 3600),
)
task_names = st.from_regex(keys.TASK_NAME_PATTERN, fullmatch=True)
task_requests = st.builds(
    m.TaskRequest,
    uav=uav_ids,
    seq=u63,
    task=task_names,
    stamp_ns=u63,
    budget_ms=reals(0, 1e6),
    body=st.binary(max_size=256),
)
task_answers = st.builds(
    m.TaskAnswer,
    uav=uav_ids,
    seq=u63,
    task=task_names,
    stamp_ns=u63,
    handle_ms=reals(0, 1e6),
    replica=st.text(max_size=64),
    body=st.binary(max_size=256),
)
mission_requests = st.builds(
    m.MissionRequest,
    uav=uav_ids,
    seq=u63,
    stamp_ns=u63,
    waypoints_m=st.lists(vec(3, -1e4, 1e4), min_size=2, max_size=m.MAX_MISSION_WAYPOINTS).map(tuple),
    speed_mps=reals(0, 50),
    source=st.text(max_size=64),
)
any_message = st.one_of(
    states,
    commands(),
    frames,
    acks,
    detections(),
    references(),
    statuses,
    qos_requests,
    qos_grants,
    mission_requests,
    qos_decisions,
    qos_monitorings,
    task_requests,
    task_answers,
)


@given(any_message)
def test_every_message_round_trips(message: m.Message) -> None:
    data = m.encode(message)
    decoded = m.decode(data)
    assert decoded == message
    assert type(decoded) is type(message)
    assert m.decode_as(data, type(message)) == message


@given(any_message)
def test_type_and_version_travel_in_every_payload(message: m.Message) -> None:
    body = msgpack.unpackb(m.encode(message), raw=False)
    assert body["t"] == message.TYPE
    assert body["v"] == m.SCHEMA_VERSION
    assert "seq" in body


@settings(max_examples=1500)
@given(st.binary(max_size=4096))
def test_arbitrary_bytes_give_decode_error_only(data: bytes) -> None:
    with contextlib.suppress(DecodeError):
        m.decode(data)


@given(any_message, st.data())
def test_truncated_messages_give_decode_error(message: m.Message, data: st.DataObject) -> None:
    encoded = m.encode(message)
    cut = data.draw(st.integers(0, len(encoded) - 1))
    with pytest.raises(DecodeError):
        m.decode(encoded[:cut])


@settings(max_examples=1000)
@given(any_message, st.data())
def test_corrupted_messages_never_raise_anything_but_decode_error(
    message: m.Message, data: st.DataObject
) -> None:
    encoded = bytearray(m.encode(message))
    for _ in range(data.draw(st.integers(1, 8))):
        encoded[data.draw(st.integers(0, len(encoded) - 1))] = data.draw(st.integers(0, 255))
    try:
        decoded = m.decode(bytes(encoded))
    except DecodeError:
        return
    assert isinstance(decoded, m.Message)


json_like = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=20,
)


@given(st.sampled_from(list(m.MESSAGE_TYPES.values())), st.data())
def test_wrong_typed_fields_give_decode_error_naming_the_field(
    cls: type[m.Message], data: st.DataObject
) -> None:
    example = data.draw(
        {
            m.State: states,
            m.Command: commands(),
            m.CameraFrame: frames,
            m.CameraAck: acks,
            m.Detections: detections(),
            m.Reference: references(),
            m.SupervisorStatus: statuses,
            m.QosRequest: qos_requests,
            m.QosGrant: qos_grants,
            m.QosDecision: qos_decisions,
            m.QosMonitoring: qos_monitorings,
            m.MissionRequest: mission_requests,
            m.TaskRequest: task_requests,
            m.TaskAnswer: task_answers,
        }[cls]
    )
    body = msgpack.unpackb(m.encode(example), raw=False)
    name = data.draw(st.sampled_from([f.name for f in fields(cls)]))
    body[name] = data.draw(json_like)
    error: DecodeError | None = None
    try:
        decoded = m.decode(msgpack.packb(body, use_bin_type=True))
    except DecodeError as exc:
        error = exc
    if error is None:
        assert isinstance(decoded, cls)  # the random value happened to be valid
    else:
        assert error.field.split("[")[0] in (name, "yaw_rad", "centers_m", "vel_mps", "quat")


def _state(**overrides: Any) -> m.State:
    base = {
        "uav": "uav1",
        "seq": 1,
        "stamp_ns": 10,
        "pos_m": (0, 0, -1),
        "vel_mps": [0, 0, 0],
        "quat": (1, 0, 0, 0),
    }
    base.update(overrides)
    return m.State(**base)


def _raw(message: m.Message, **changes: Any) -> bytes:
    body = msgpack.unpackb(m.encode(message), raw=False)
    body.update(changes)
    return bytes(msgpack.packb(body, use_bin_type=True))


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"v": 2}, "v"),
        ({"v": True}, "v"),
        ({"t": "Telemetry"}, "t"),
        ({"t": 5}, "t"),
        ({"extra": 1}, "extra"),
        ({"pos_m": [0.0, math.nan, 0.0]}, "pos_m[1]"),
        ({"pos_m": [0.0, 0.0]}, "pos_m"),
        ({"quat": [0.2, 0.0, 0.0, 0.0]}, "quat"),
        ({"seq": -1}, "seq"),
        ({"seq": True}, "seq"),
        ({"uav": "bad id"}, "uav"),
        ({"rtt_est_ms": -3.0}, "rtt_est_ms"),
        ({"mode": "x" * 33}, "mode"),
    ],
)
def test_bad_state_fields_are_named(changes: dict[str, Any], field: str) -> None:
    with pytest.raises(DecodeError) as info:
        m.decode(_raw(_state(), **changes))
    assert info.value.field == field


def test_missing_field_is_named() -> None:
    body = msgpack.unpackb(m.encode(_state()), raw=False)
    del body["stamp_ns"]
    with pytest.raises(DecodeError) as info:
        m.decode(msgpack.packb(body))
    assert info.value.field == "stamp_ns"


def test_oversized_inputs_are_rejected_before_unpacking() -> None:
    with pytest.raises(DecodeError, match="exceed"):
        m.decode(b"\x00" * (m.MAX_MESSAGE_BYTES + 1))
    frame = m.CameraFrame(
        uav="u", seq=1, stamp_ns=1, kind="rgb", encoding="jpeg", width=1, height=1,
        intrinsics=(1, 1, 0, 0), payload=b"",
    )  # fmt: skip
    with pytest.raises(DecodeError, match="exceed") as info:
        m.decode(_raw(frame, payload=b"\x00" * (m.MAX_PAYLOAD_BYTES + 1)))
    assert info.value.field == "<payload>"
    with pytest.raises(DecodeError):
        m.decode(_raw(_state(), mode="x" * 5000))


@pytest.mark.parametrize(
    "data", [b"", b"\xc1", msgpack.packb([1, 2]), msgpack.packb({1: 2}), msgpack.packb({"t": "State"}) + b"x"]
)
def test_malformed_payloads(data: bytes) -> None:
    with pytest.raises(DecodeError):
        m.decode(data)


def test_decode_rejects_non_bytes_and_ext_types() -> None:
    with pytest.raises(DecodeError, match="expected bytes"):
        m.decode("State")
    with pytest.raises(DecodeError):
        m.decode(msgpack.packb(msgpack.ExtType(5, b"abc")))


def test_decode_as_checks_the_type() -> None:
    with pytest.raises(DecodeError, match="expected Command"):
        m.decode_as(m.encode(_state()), m.Command)


def test_construction_validates_and_normalises() -> None:
    state = _state(pos_m=[1, 2, 3])
    assert state.pos_m == (1.0, 2.0, 3.0)
    assert isinstance(state.pos_m[0], float)
    with pytest.raises(MessageError, match="pos_m"):
        _state(pos_m=(0, 0, math.inf))
    with pytest.raises(MessageError, match="yaw_rad"):
        m.Command(
            uav="u", seq=0, state_seq=0, state_stamp_ns=0, edge_hold_ns=0, dt_s=0.05,
            accel_mps2=[(0, 0, 0)], yaw_rad=[0, 0],
        )  # fmt: skip
    with pytest.raises(MessageError, match="focal"):
        m.CameraFrame(
            uav="u", seq=1, stamp_ns=1, kind="rgb", encoding="jpeg", width=1, height=1,
            intrinsics=(0, 1, 0, 0), payload=b"",
        )  # fmt: skip
    with pytest.raises(MessageError, match="centers_m"):
        m.Detections(uav="u", seq=0, frame_seq=0, stamp_ns=0, circles_px=[(1, 1, 1)])
    with pytest.raises(MessageError, match="vel_mps"):
        m.Reference(uav="u", seq=0, stamp_ns=0, dt_s=0.1, pos_m=[(0, 0, 0)], vel_mps=[], yaw_rad=[0])
    with pytest.raises(MessageError, match="kind"):
        m.CameraAck(uav="u", seq=0, frame_seq=0, kind="ir", stamp_ns=0, edge_hold_ns=0)
    with pytest.raises(MessageError, match="payload"):
        m.CameraFrame(
            uav="u", seq=1, stamp_ns=1, kind="rgb", encoding="jpeg", width=1, height=1,
            intrinsics=(1, 1, 0, 0), payload="text",  # type: ignore[arg-type]
        )  # fmt: skip
    with pytest.raises(MessageError, match="watchdog"):
        replace(_status(), watchdog=1)  # type: ignore[arg-type]
    assert m.CameraFrame(
        uav="u", seq=1, stamp_ns=1, kind="rgb", encoding="jpeg", width=1, height=1,
        intrinsics=(1, 1, 0, 0), payload=bytearray(b"ab"),  # type: ignore[arg-type]
    ).payload == b"ab"  # fmt: skip


def _status() -> m.SupervisorStatus:
    return status(uav="u", seq=0)


def test_every_control_source_travels_and_unknown_ones_are_rejected() -> None:
    for source in ControlSource:  # the FC-silence hold included: the daemon must be able to report it
        status = replace(_status(), control_source=source)
        assert m.decode(m.encode(status)) == status
        assert m.decode(m.encode(status)).control_source is source
    body = msgpack.unpackb(m.encode(_status()), raw=False)
    for name, bad in (
        ("control_source", "fc-lost"),
        ("flow", "best-effort"),
        ("camera_flow", ""),
        ("state", "q7"),
    ):
        with pytest.raises(DecodeError, match=name):
            m.decode(msgpack.packb({**body, name: bad}, use_bin_type=True))
