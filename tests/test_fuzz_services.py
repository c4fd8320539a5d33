"""Bad input on every subscribed key, over real zenoh, to the real services.

Random bytes, truncated messages, wrong schema versions, messages of the wrong type, a message for
another drone on a drone's key, and oversized payloads go to the MPC, planner, detector and onboard
daemon. Each must count every one as rejected (read from its health line) and keep serving valid
traffic. No sleeps: a valid message sent after the bad ones on the same key and priority arrives
after them, so once the service has answered it, it has seen every bad one.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import (
    MAX_MESSAGE_BYTES,
    CameraAck,
    CameraFrame,
    Command,
    Detections,
    Message,
    Reference,
    State,
    encode,
)  # fmt: skip
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Priority, Publisher, Received, Role, open_bus
from tests.conftest import flow_ports, free_tcp_port
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]
SUPPRESS = [HealthCheck.too_slow, HealthCheck.function_scoped_fixture]

STATE = State(uav="uav1", seq=1, stamp_ns=1, pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
              quat=(1.0, 0.0, 0.0, 0.0), rtt_est_ms=5.0)  # fmt: skip
COMMAND = Command(uav="uav1", seq=1, state_seq=1, state_stamp_ns=1, edge_hold_ns=0, dt_s=0.05,
                  accel_mps2=((0.0, 0.0, 0.0),), yaw_rad=(0.0,))  # fmt: skip
ACK = CameraAck(uav="uav1", seq=1, frame_seq=1, kind="rgb", stamp_ns=1, edge_hold_ns=0)
DETECTIONS = Detections(uav="uav1", seq=1, frame_seq=1, stamp_ns=1)
REFERENCE = Reference(uav="uav1", seq=1, stamp_ns=1, dt_s=0.05, pos_m=((0.0, 0.0, -1.5),),
                      vel_mps=((0.0, 0.0, 0.0),), yaw_rad=(0.0,))  # fmt: skip
FRAME = CameraFrame(uav="uav1", seq=1, stamp_ns=1, kind="rgb", encoding="jpeg", width=8, height=8,
                    intrinsics=(5.0, 5.0, 4.0, 4.0), payload=b"\xff\xd8\xff")  # fmt: skip

# key -> (a valid message for it, a valid message of another type for it)
KEYS: dict[str, tuple[Message, Message]] = {
    keys.uplink("uav1", Flow.PRIORITY, Stream.STATE): (STATE, COMMAND),
    keys.downlink("uav1", Downlink.REFERENCE): (REFERENCE, STATE),
    keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB): (FRAME, STATE),
    keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_DEPTH): (FRAME, ACK),
    keys.downlink("uav1", Downlink.COMMAND): (COMMAND, STATE),
    keys.downlink("uav1", Downlink.CAMERA_ACK): (ACK, COMMAND),
    keys.downlink("uav1", Downlink.DETECTIONS): (DETECTIONS, REFERENCE),
}


def _rewrite(message: Message, **changes: object) -> bytes:
    body = msgpack.unpackb(encode(message), raw=False)
    body.update(changes)
    return bytes(msgpack.packb(body, use_bin_type=True))


def bad_payloads(valid: Message, other: Message) -> st.SearchStrategy[bytes]:
    good = encode(valid)
    return st.one_of(
        st.binary(max_size=3000),
        st.integers(0, len(good) - 1).map(lambda n: good[:n]),  # truncated
        st.integers(-5, 100).filter(lambda v: v != 1).map(lambda v: _rewrite(valid, v=v)),  # wrong version
        st.just(encode(other)),  # a valid message of the wrong type for this key
        st.just(_rewrite(valid, uav="uav2")),  # another drone speaking on uav1's key
        st.sampled_from(["seq", "stamp_ns"]).map(lambda f: _rewrite(valid, **{f: -1})),  # out of range
    )


@pytest.fixture(scope="module")
def services(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[tuple[ZenohConfig, dict[str, DynqosProcess]]]:
    tmp = tmp_path_factory.mktemp("fuzz")
    zcfg = ZenohConfig(**flow_ports())
    config = tmp / "fuzz.toml"
    config.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        '[onboard]\ncamera = "none"\nfallback = "continue"\nhealth_interval_s = 1\n'
        f'mavlink_url = "udpin:127.0.0.1:{free_tcp_port()}"\n'
    )
    procs: dict[str, DynqosProcess] = {}
    try:
        for name, args in (("router", ["edge", "router"]), ("mpc", ["edge", "mpc"]),
                           ("planner", ["edge", "planner"]), ("detector", ["edge", "detector"]),
                           ("onboard", ["onboard"])):  # fmt: skip
            procs[name] = DynqosProcess(args, config)
        yield zcfg, procs
    finally:
        for proc in reversed(procs.values()):
            proc.stop()


def _answered(bus: Bus, pub: Publisher, message: Message, reply_key: str, kind: type[Message]) -> bool:
    """Send `message` on `pub` and wait for a `kind` on `reply_key` (the service is alive and has
    processed everything sent before)."""
    replies: BoundedQueue[Received] = BoundedQueue(64)
    bus.subscribe(reply_key, replies)
    pub.put(message)
    while (item := replies.get(20)) is not None:
        if isinstance(item.message, kind):
            return True
    return False


def test_every_bad_message_is_rejected_and_valid_traffic_still_served(
    services: tuple[ZenohConfig, dict[str, DynqosProcess]],
) -> None:
    zcfg, procs = services
    for name in ("mpc", "planner"):  # they subscribe to uav1 once its daemon announces it (edge/feeds.py)
        assert any(f"{name}: following drone uav1" in line for line in procs[name].lines(timeout_s=20))
    bus = open_bus(zcfg, Role.EDGE)
    sent = dict.fromkeys(KEYS, 0)
    try:
        pubs = {key: bus.publisher(key, Priority.DATA) for key in KEYS}
        for pub in pubs.values():
            assert pub.wait_matched(20)
        for key, (valid, other) in KEYS.items():
            _storm(pubs[key], bad_payloads(valid, other), sent, key)
        for key in (
            keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB),
            keys.downlink("uav1", Downlink.COMMAND),
        ):
            pubs[key].put_bytes(b"\x00" * (MAX_MESSAGE_BYTES + 1))  # oversized: refused before parsing
            sent[key] += 1
        # Valid traffic after the storm, on the same keys: every service still answers.
        state_key = keys.uplink("uav1", Flow.PRIORITY, Stream.STATE)
        frame_key = keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB)
        command_key, ack_key = (
            keys.downlink("uav1", Downlink.COMMAND),
            keys.downlink("uav1", Downlink.CAMERA_ACK),
        )
        assert _answered(bus, pubs[state_key], _with(STATE, seq=10**6), command_key, Command)
        assert _answered(bus, pubs[frame_key], _with(FRAME, seq=10**6), ack_key, CameraAck)
        for kind in (Downlink.COMMAND, Downlink.CAMERA_ACK, Downlink.DETECTIONS):
            key = keys.downlink("uav1", kind)
            pubs[key].put(KEYS[key][0])  # the onboard daemon gets valid ones after the bad ones
    finally:
        bus.close()
    logs = {name: procs[name].stop() for name in ("mpc", "planner", "detector", "onboard")}
    for name in logs:
        assert "Traceback" not in logs[name], logs[name][-2000:]
        # each stopped on its SIGTERM and said so: its last counters are in its "stopped" line
        assert not procs[name].killed, (procs[name].ended(), logs[name][-2000:])
        assert procs[name].returncode == 0, (procs[name].ended(), logs[name][-2000:])
    state_key = keys.uplink("uav1", Flow.PRIORITY, Stream.STATE)
    ref_key = keys.downlink("uav1", Downlink.REFERENCE)
    rgb = keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB)
    depth = keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_DEPTH)
    down = [keys.downlink("uav1", k) for k in (Downlink.COMMAND, Downlink.CAMERA_ACK, Downlink.DETECTIONS)]
    # the MPC reads the drone's states and references; not the commands (its replicas' beats tell it
    # who is alive, edge/replicas.py), so a bad command never reaches it
    assert _last(logs["mpc"], "rejected") == sent[state_key] + sent[ref_key]
    # a standby planner reads its replicas' references for their mission time
    assert _last(logs["planner"], "rejected") == sent[state_key] + sent[ref_key]
    assert _last(logs["detector"], "rejected") == sent[rgb] + sent[depth]
    assert _last(logs["onboard"], "bad_downlink") == sum(sent[k] for k in down) + sent[ref_key]


def _storm(pub: Publisher, payloads: st.SearchStrategy[bytes], sent: dict[str, int], key: str) -> None:
    """Hypothesis' examples of bad payloads, each published on `key` and counted."""

    @given(payload=payloads)
    @settings(max_examples=40, deadline=None, database=None, suppress_health_check=SUPPRESS)
    def send(payload: bytes) -> None:
        pub.put_bytes(payload)
        sent[key] += 1

    send()


def _with(message: Message, **changes: object) -> Message:
    from dataclasses import replace

    return replace(message, **changes)


def _last(log: str, counter: str) -> int:
    values = re.findall(rf"\b{counter}=(\d+)", log)
    assert values, log[-2000:]
    return int(values[-1])
