"""dynqos messages as Foxglove channels (dynqos/observers/telemetry.py): each conversion decoded back with the
schema the channel advertises (protobuf for Foxglove's well-known schemas, JSON schema for dynqos's
own), so a wrong field or frame is seen as a wrong value."""

from __future__ import annotations

from typing import Any

import jsonschema
import pytest

from dynqos.common.messages import (
    CameraFrame,
    Detections,
    QosDecision,
    QosGrant,
    Reference,
    State,
    SupervisorStatus,
)
from dynqos.observers.telemetry import JSON_SCHEMAS, Telemetry, frames, json_schema_for, world_scene
from dynqos.sim.vehicle.world import default_world
from tests.statuses import status

pb = pytest.importorskip("google.protobuf")
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from google.protobuf.json_format import MessageToDict  # noqa: E402

NOW = 1_763_880_000_123_456_789


def decode(message: Any) -> dict[str, Any]:
    """A foxglove message through its own advertised schema (a protobuf FileDescriptorSet)."""
    schema = message.get_schema()
    assert schema.encoding == "protobuf"
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
        pool.Add(file)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
    return MessageToDict(cls.FromString(message.encode()))


def _state(z: float = -1.5) -> State:
    return State(
        uav="uav1", seq=3, stamp_ns=5, pos_m=(1.0, 2.0, z), vel_mps=(0, 0, 0), quat=(1.0, 0.0, 0.0, 0.0)
    )


def _status(state: str, risk: str = "MR", cause: str = "") -> SupervisorStatus:
    return status(
        stamp_ns=7,
        state=state,
        flow="priority" if state != "q1" else "default",
        latency="HL",
        risk=risk,
        spaciousness_m=3.2,
        p_cam=0.1,
        p_cc=0.2,
        p_lat=0.6,
        cause=cause,
        changed_ns=1,
        rtt_ms=21.5,
    )


def test_a_state_is_a_pose_in_the_ned_frame_stamped_on_the_common_time_base() -> None:
    [(topic, pose)] = Telemetry().convert(_state(), NOW)
    assert topic == "/uav1/pose"
    got = decode(pose)
    assert got["frameId"] == "ned"
    assert got["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": -1.5}
    assert got["pose"]["orientation"] == {"w": 1.0}  # zero fields are left out by protobuf
    assert got["timestamp"] == "2025-11-23T06:40:00.123456789Z"


def test_a_status_feeds_the_status_channel_the_scene_and_a_log_line_on_each_change() -> None:
    telemetry = Telemetry()
    assert [t for t, _ in telemetry.convert(_status("q1", "LR"), NOW)] == ["/uav1/status"]  # no pose yet
    telemetry.convert(_state(), NOW)
    outs = dict(telemetry.convert(_status("q3", "HR", "MR and HL"), NOW + 1))
    status = outs["/uav1/status"]
    jsonschema.validate(status, JSON_SCHEMAS["status"])
    assert (status["state"], status["flow"], status["rtt_ms"], status["p_lat"]) == (
        "q3",
        "priority",
        21.5,
        0.6,
    )
    scene = decode(outs["/uav1/scene"])
    entities = {e["id"]: e for e in scene["entities"]}
    zone = entities["uav1/risk"]["spheres"][0]
    assert zone["pose"]["position"] == {"x": 1.0, "y": 2.0, "z": -1.5}  # around the drone
    assert zone["color"]["r"] > 0.8 > zone["color"]["g"]  # HR is red
    assert "q3 HR priority" in entities["uav1/body"]["texts"][0]["text"]
    line = decode(outs["/log"])
    assert line["message"] == "uav1: q1 -> q3 (MR and HL)"
    assert "/log" not in dict(telemetry.convert(_status("q3", "HR"), NOW + 2))  # no change, no line


def test_images_detections_references_and_the_qos_messages() -> None:
    telemetry = Telemetry()
    jpeg = b"\xff\xd8\xff\xe0 a jpeg"
    frame = CameraFrame(uav="uav1", seq=4, stamp_ns=1, kind="rgb", encoding="jpeg", width=64, height=48,
                        intrinsics=(50.0, 50.0, 32.0, 24.0), payload=jpeg)  # fmt: skip
    [(topic, image)] = telemetry.convert(frame, NOW)
    assert topic == "/uav1/camera/rgb"
    got = decode(image)
    assert got["format"] == "jpeg"
    assert __import__("base64").b64decode(got["data"]) == jpeg
    depth = CameraFrame(uav="uav1", seq=4, stamp_ns=1, kind="depth", encoding="zstd16", width=64, height=48,
                        intrinsics=(50.0, 50.0, 32.0, 24.0), payload=b"x")  # fmt: skip
    assert telemetry.convert(depth, NOW) == []  # depth is not drawn
    detections = Detections(uav="uav1", seq=1, frame_seq=4, stamp_ns=1, circles_px=((30.0, 20.0, 8.0),),
                            centers_m=((0.1, 0.2, 2.5, 0.4),))  # fmt: skip
    outs = dict(telemetry.convert(detections, NOW))
    jsonschema.validate(outs["/uav1/detections"], JSON_SCHEMAS["detections"])
    circle = decode(outs["/uav1/camera/annotations"])["circles"][0]
    assert (circle["position"], circle["diameter"]) == ({"x": 30.0, "y": 20.0}, 16.0)
    ref = Reference(uav="uav1", seq=1, stamp_ns=1, dt_s=0.1, pos_m=((0, 0, -1.5), (0.1, 0, -1.5)),
                    vel_mps=((0, 0, 0), (0, 0, 0)), yaw_rad=(0.0, 0.0))  # fmt: skip
    [(topic, scene)] = telemetry.convert(ref, NOW)
    assert topic == "/uav1/scene"
    points = decode(scene)["entities"][0]["lines"][0]["points"]
    assert len(points) == 2
    grant = QosGrant(uav="uav1", seq=1, grant="available", backend="camara", session_id="s1")
    [(topic, as_json)] = telemetry.convert(grant, NOW)
    assert json_schema_for(topic) is JSON_SCHEMAS["qos/grant"]
    jsonschema.validate(as_json, JSON_SCHEMAS["qos/grant"])
    decision = QosDecision(uav="uav1", seq=1, stamp_ns=1, action="grant", reason="HR", risk="HR",
                           latency_excess=0.0, holders=("uav1",))  # fmt: skip
    outs = dict(telemetry.convert(decision, NOW))
    jsonschema.validate(outs["/uav1/qos/decision"], JSON_SCHEMAS["qos/decision"])
    assert decode(outs["/log"])["message"] == "uav1: arbiter grant: HR"


def test_the_world_and_the_frames() -> None:
    world = default_world()
    topic, scene = world_scene(world, NOW)
    assert topic == "/world"
    entities = decode(scene)["entities"]
    assert len(entities) == len(world.cylinders) + len(world.boxes) + len(world.hoops)
    topic, transforms = frames(NOW)
    (transform,) = decode(transforms)["transforms"]
    assert (transform["parentFrameId"], transform["childFrameId"]) == ("world", "ned")
    assert transform["rotation"] == {"x": 1.0}  # half a turn about x: NED's z down becomes up


def test_the_shipped_foxglove_layout_is_current_and_reads_only_what_is_published() -> None:
    import json
    import re
    from pathlib import Path

    from dynqos.observers.layout import layout_json

    shipped = (Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json").read_text()
    assert shipped == layout_json(), (
        "docs/foxglove-layout.json is stale: python -m dynqos.observers.layout > it"
    )
    text = json.dumps(json.loads(shipped))
    telemetry = Telemetry()
    published = {"/tf", "/world", "/log"}
    for message in (_state(), _status("q1"), _status("q3", cause="x")):
        published |= {t for t, _ in telemetry.convert(message, NOW)}
    published |= {"/uav1/camera/rgb", "/uav1/camera/annotations"}  # from the image tests above
    topics = set(re.findall(r'"(/[a-z0-9/_]+?)(?:\.[a-z_]+)?"', text))
    assert topics <= published, topics - published
    fields = set(re.findall(r'"/uav1/status\.([a-z_]+)"', text))
    assert fields
    assert fields <= set(JSON_SCHEMAS["status"]["properties"])
    panels = set(re.findall(r'"panelType": "(\w+)"', text))
    assert {"ThreeDee", "Image", "Plot", "StateTransitions", "Log"} <= panels
