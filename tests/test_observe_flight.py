"""`dynqos view` and `dynqos record` on a real short flight (docs/observability.md): a WebSocket client
speaking the Foxglove protocol sees the channels advertised with their schemas and receives poses,
images and the status with sane values; the MCAP written by `dynqos record` has a schema on every
channel, as many poses and statuses as the drone published, log times that only grow, and the
metadata (version, configuration) that makes it self-describing.
"""

from __future__ import annotations

import base64
import json
import queue
import signal
import struct
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from dynqos.common.config import ZenohConfig
from dynqos.common.messages import State, SupervisorStatus, decode, encode
from dynqos.common.transport import Role, open_session
from tests.conftest import flow_ports, free_tcp_port
from tests.procs import DynqosProcess
from tests.statuses import status
from tests.test_onboard_loop import loop_config

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

websockets = pytest.importorskip("websockets.sync.client")
mcap_reader = pytest.importorskip("mcap.reader")
pytest.importorskip("google.protobuf")
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from google.protobuf.json_format import MessageToDict  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"  # what the SDK's server accepts (the app also speaks foxglove.websocket.v1)
MESSAGE_DATA = 0x01


def _protobuf(schema_name: str, descriptor: bytes, payload: bytes) -> dict[str, Any]:
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(descriptor).file:
        pool.Add(file)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    return MessageToDict(cls.FromString(payload))


class FoxgloveClient:
    """The Foxglove WebSocket protocol from the client's side: advertisements, subscriptions, data."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        assert ws.subprotocol == SUBPROTOCOL
        self.channels: dict[str, dict[str, Any]] = {}  # by topic
        self.by_subscription: dict[int, dict[str, Any]] = {}
        self.server_info: dict[str, Any] = {}

    def read(self) -> tuple[dict[str, Any], bytes] | None:
        """One frame: control messages are taken in, a message on a subscription is returned."""
        frame = self.ws.recv(timeout=30)  # the viewer runs niced: on a loaded machine it may lag
        if isinstance(frame, str):
            body = json.loads(frame)
            if body["op"] == "serverInfo":
                self.server_info = body
            elif body["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in body["channels"]})
            return None
        assert frame[0] == MESSAGE_DATA
        subscription, _log_time = struct.unpack_from("<IQ", frame, 1)
        return self.by_subscription[subscription], frame[13:]

    def wait_for_topics(self, topics: set[str]) -> None:
        for _ in range(2000):
            if topics <= set(self.channels):
                return
            self.read()
        raise AssertionError(f"never advertised: {topics - set(self.channels)}")

    def subscribe(self, topics: list[str]) -> None:
        subs = []
        for i, topic in enumerate(topics, start=1):
            self.by_subscription[i] = self.channels[topic]
            subs.append({"id": i, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decode(self, channel: dict[str, Any], payload: bytes) -> dict[str, Any]:
        if channel["encoding"] == "json":
            decoded: dict[str, Any] = json.loads(payload)
            return decoded
        assert channel["encoding"] == "protobuf"
        return _protobuf(channel["schemaName"], base64.b64decode(channel["schema"]), payload)


def test_view_and_record_a_short_flight(tmp_path: Path) -> None:
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg)
    mcap_path = tmp_path / "flight.mcap"
    procs: dict[str, DynqosProcess] = {}
    counted: dict[str, int] = {"state": 0, "status": 0}
    status_seqs: set[int] = set()
    seen: queue.Queue[str] = queue.Queue()
    enough_states = threading.Event()  # over a second of the drone's states: a recording worth reading
    observer = sentinel_drone = None
    logs: dict[str, str] = {}
    try:
        procs["router"] = DynqosProcess(["edge", "router"], config)
        procs["vehicle"] = DynqosProcess(["sim", "vehicle", "--duration", "600"], config)
        for service in ("planner", "mpc", "detector"):
            procs[service] = DynqosProcess(["edge", service], config)
        procs["record"] = DynqosProcess(["record", "--out", str(mcap_path)], config)
        view_port = free_tcp_port()
        procs["view"] = DynqosProcess(["view", "--port", str(view_port)], config)
        assert procs["view"].info["port"] == view_port

        observer = open_session(zcfg, Role.EDGE)

        def count(sample: Any) -> None:
            message = decode(bytes(sample.payload))
            if message.uav == "uav9":
                seen.put(type(message).__name__)
            elif isinstance(message, State):
                counted["state"] += 1
                if counted["state"] > 20:
                    enough_states.set()
            elif isinstance(message, SupervisorStatus):
                counted["status"] += 1
                status_seqs.add(message.seq)

        subscribers = [
            observer.declare_subscriber(k, count) for k in ("dynqos/*/up/*/state", "dynqos/*/up/*/status")
        ]
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config)

        url = f"ws://127.0.0.1:{view_port}"
        with websockets.connect(url, subprotocols=[SUBPROTOCOL], open_timeout=10) as ws:
            _check_the_live_view(FoxgloveClient(ws))
        # the live view may be seen within a second of the drone's start: record more than that
        assert enough_states.wait(timeout=30), f"the drone sent {counted['state']} states in 30 s"
        procs.pop("onboard").stop()  # every state and status the drone sent is now on its way
        # Sentinels from a drone's session like uav1's (two links, the same priorities): a state on the
        # priority flow and a status on the default flow, each behind what uav1 sent on that path.
        sentinel_drone = open_session(zcfg, Role.DRONE)
        sentinel_drone.put(
            "dynqos/uav9/up/priority/state", encode(_sentinel_state()), priority=zenoh.Priority.REAL_TIME
        )
        sentinel_drone.put(
            "dynqos/uav9/up/default/status", encode(_sentinel_status()), priority=zenoh.Priority.DATA_HIGH
        )
        assert {seen.get(timeout=10), seen.get(timeout=10)} == {"State", "SupervisorStatus"}
        procs["record"].proc.send_signal(signal.SIGTERM)
        record_log = procs.pop("record").stop()
        del subscribers
    except (AssertionError, TimeoutError) as failure:
        logs = {name: procs[name].stop() for name in reversed(list(procs))}
        tails = {name: log.splitlines()[-3:] for name, log in logs.items()}
        raise AssertionError(f"{failure}; the services' last log lines: {tails}") from failure
    finally:
        for session in (sentinel_drone, observer):
            if session is not None:
                session.close()  # type: ignore[no-untyped-call]
        for name in reversed(list(procs)):
            procs[name].stop()
    assert "record: stopped" in record_log
    _check_the_recording(mcap_path, counted, status_seqs)


def _check_the_live_view(client: FoxgloveClient) -> None:
    wanted = ["/uav1/pose", "/uav1/camera/rgb", "/uav1/status"]
    client.wait_for_topics({*wanted, "/tf", "/world", "/uav1/scene"})
    assert client.server_info["name"] == "dynqos"
    for topic in wanted:
        channel = client.channels[topic]
        assert channel["schemaName"], topic  # every channel has its schema
        assert channel["schema"], topic
    assert client.channels["/uav1/pose"]["schemaName"] == "foxglove.PoseInFrame"
    assert client.channels["/uav1/camera/rgb"]["schemaName"] == "foxglove.CompressedImage"
    assert json.loads(client.channels["/uav1/status"]["schema"])["title"] == "dynqos.SupervisorStatus"
    client.subscribe(wanted)
    got: dict[str, list[dict[str, Any]]] = {topic: [] for topic in wanted}
    deadline = time.monotonic() + 90  # a closed loop shows an RTT within seconds of take-off
    while time.monotonic() < deadline:
        item = client.read()
        if item is not None:
            channel, payload = item
            got[channel["topic"]].append(client.decode(channel, payload))
            if all(len(v) >= 3 for v in got.values()) and any(s.get("rtt_ms") for s in got["/uav1/status"]):
                break
    assert all(len(v) >= 3 for v in got.values()), {k: len(v) for k, v in got.items()}
    assert any(s.get("rtt_ms") for s in got["/uav1/status"]), got["/uav1/status"][-3:]
    for pose in got["/uav1/pose"]:
        assert pose["frameId"] == "ned"
        position = pose["pose"]["position"]
        assert -3.5 <= position.get("z", 0.0) <= 0.5  # NED: on the ground or up to 3.5 m above it
        assert abs(position.get("x", 0.0)) < 4  # inside the arena
        assert abs(position.get("y", 0.0)) < 4
    for image in got["/uav1/camera/rgb"]:
        assert image["format"] == "jpeg"
        assert base64.b64decode(image["data"])[:3] == b"\xff\xd8\xff"  # a JPEG
    rtts = [s["rtt_ms"] for s in got["/uav1/status"] if s.get("rtt_ms")]
    assert rtts
    assert all(0 < r < 500 for r in rtts)
    assert {s["state"] for s in got["/uav1/status"]} <= {"q1", "q2", "q3", "q4", "q5", "q6", "qA"}


def _sentinel_state() -> State:
    return State(uav="uav9", seq=1, stamp_ns=1, pos_m=(0, 0, 0), vel_mps=(0, 0, 0), quat=(1, 0, 0, 0))


def _sentinel_status() -> SupervisorStatus:
    return status(uav="uav9", stamp_ns=1)


def _check_the_recording(path: Path, counted: dict[str, int], status_seqs: set[int]) -> None:
    with path.open("rb") as stream:
        reader = mcap_reader.make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None  # closed cleanly: the summary and footer were written
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        per_topic: dict[str, list[int]] = {}
        recorded_seqs: set[int] = set()
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None, channel.topic  # every channel has its schema
            assert schema.data, channel.topic
            per_topic.setdefault(channel.topic, []).append(message.log_time)
            if channel.topic == "/uav1/status":
                recorded_seqs.add(json.loads(message.data)["seq"])
    assert metadata["dynqos"]["version"] == __import__("dynqos").__version__
    assert "[zenoh]" in metadata["dynqos.config"]["toml"]
    for topic, times in per_topic.items():
        assert times == sorted(times), topic  # log times only grow on each channel
    assert len(per_topic["/uav1/pose"]) == counted["state"] > 20  # every state the drone sent
    assert recorded_seqs == status_seqs, (
        sorted(status_seqs - recorded_seqs),
        sorted(recorded_seqs - status_seqs),
    )
    assert len(per_topic["/uav1/status"]) == counted["status"] > 3
    assert len(per_topic["/uav9/pose"]) == len(per_topic["/uav9/status"]) == 1
    assert per_topic["/uav1/camera/rgb"]
    assert {"/tf", "/world", "/uav1/scene"} <= set(per_topic)
