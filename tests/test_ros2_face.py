"""`dynqos edge ros2` against independent ROS 2 clients over zenoh: the ROBOTIS zenoh-ros2-sdk lists
the drone's topics with their types and hashes as `ros2 topic list -t` would, and a raw zenoh
subscriber on the rmw_zenoh data keys counts every sample, checks its attachment (rmw_zenoh drops a
sample without one) and decodes it with rosbags against what the drone published (docs/ros2.md)."""

from __future__ import annotations

import math
import queue
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import zenoh
from zenoh_ros2_sdk import get_topic_info, get_topic_names_and_types

from dynqos.common import keys
from dynqos.common.config import load_config
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import (
    CameraFrame,
    Detections,
    MissionRequest,
    QosDecision,
    QosGrant,
    State,
    decode,
)
from dynqos.common.modes import Grant
from dynqos.common.transport import Priority, Role, default_flow_endpoint, open_bus
from dynqos.edge.ros2 import codec, wire
from tests.conftest import free_tcp_port
from tests.procs import DynqosProcess
from tests.ros2_client import first_sample, ros_client, ros_pose, sdk_publisher
from tests.statuses import status as quiet

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

STATES = 40


@pytest.fixture(scope="module")
def edge(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, int]]:
    """One router and one bridge for the module: the SDK's discovery keeps its first router's session."""
    port = free_tcp_port()
    config = tmp_path_factory.mktemp("ros2") / "edge.toml"
    config.write_text(
        f'[zenoh]\ndefault_port = {port}\npriority_port = {free_tcp_port()}\n[ros2]\nprefix = "fleet"\n'
    )
    router = DynqosProcess(["edge", "router"], config)
    face = DynqosProcess(["edge", "ros2"], config)
    try:
        yield config, port
    finally:
        face.stop()
        router.stop()


def _states() -> list[State]:
    h = math.sqrt(0.5)
    return [
        State(
            uav="uav7",
            seq=k,
            stamp_ns=k,
            pos_m=(0.1 * k, 2.0, -2.5),
            vel_mps=(1.0, 0.0, 0.0),
            quat=(h, 0.0, 0.0, h),
        )
        for k in range(1, STATES + 1)
    ]


def test_a_drones_pose_reaches_ros2_clients_counted_with_attachments_and_tokens(
    edge: tuple[Path, int],
) -> None:
    config_path, port = edge
    config = load_config(config_path)
    got: queue.Queue[zenoh.Sample] = queue.Queue()
    ros_side = ros_client(port)
    drone = open_bus(config.zenoh, Role.DRONE, connect=[default_flow_endpoint(config.zenoh)])
    try:
        pose_key = wire.topic_key(0, "/fleet/uav7/pose", codec.POSE, codec.type_hash(codec.POSE))
        ros_side.declare_subscriber(pose_key, got.put)
        publisher = drone.publisher(keys.uplink("uav7", Flow.DEFAULT, Stream.STATE), Priority.DATA_HIGH)
        assert publisher.wait_matched(10)  # the bridge subscribes to every drone's state
        states = _states()
        publisher.put(states[0])
        samples = [got.get(timeout=10)]  # the bridge declared the topic on the first state
        for state in states[1:]:
            publisher.put(state)
        samples += [got.get(timeout=10) for _ in states[1:]]
        # every sample counted: one pose per state, each with rmw_zenoh's attachment, in order
        attachments = [wire.Attachment.decode(s.attachment.to_bytes()) for s in samples]
        assert [a.sequence for a in attachments] == list(range(1, STATES + 1))
        assert len({a.gid for a in attachments}) == 1
        for state, sample in zip(states, samples, strict=True):
            pose = codec.decode(codec.POSE, sample.payload.to_bytes())
            p = pose.pose.position
            assert (p.x, p.y, p.z) == pytest.approx((2.0, state.pos_m[0], 2.5))  # ENU
            assert pose.header.frame_id == "map"
        # an independent ROS 2 client lists the topics with their types, as `ros2 topic list -t` does
        topics = dict(get_topic_names_and_types(domain_id=0, router_port=port, timeout=2.0))
        assert topics["/fleet/uav7/pose"] == [codec.POSE]
        assert topics["/fleet/uav7/odom"] == [codec.ODOMETRY]
        assert topics["/tf"] == ["tf2_msgs/msg/TFMessage"]
        info = get_topic_info("/fleet/uav7/pose", domain_id=0, router_port=port, timeout=2.0, verbose=True)
        assert info is not None
        (endpoint,) = info.publishers
        assert endpoint.node_name == "dynqos_edge"
        assert endpoint.node_namespace == "/fleet"
        assert endpoint.type_hash == codec.type_hash(codec.POSE)
        assert endpoint.qos == "::,10:,:,:,,"  # reliable, depth 10, as rmw_zenoh writes it

        # the supervisor's status, as diagnostic_msgs/DiagnosticArray: the fallback flying is an error
        status_key = wire.topic_key(
            0, "/fleet/uav7/status", codec.DIAGNOSTICS, codec.type_hash(codec.DIAGNOSTICS)
        )
        ros_side.declare_subscriber(status_key, got.put)
        status_pub = drone.publisher(keys.uplink("uav7", Flow.DEFAULT, Stream.STATUS), Priority.DATA_HIGH)
        assert status_pub.wait_matched(10)
        status = quiet(
            uav="uav7",
            stamp_ns=1,
            state="qA",
            flow="priority",
            camera_flow="priority",
            camera_rate_factor=0.5,
            control_source="fallback",
            latency="HL",
            risk="HR",
            watchdog=True,
            p_lat=0.9,
            prev_state="q2",
            cause="watchdog",
            changed_ns=1,
            rtt_ms=180.25,
        )
        # the subscriber to the status topic may not be known to the bridge's publisher, declared with it:
        # the status is sent until one arrives (bounded)
        sample = first_sample(got, lambda: status_pub.put(status))
        (diagnostic,) = codec.decode(codec.DIAGNOSTICS, sample.payload.to_bytes()).status
        assert diagnostic.level == codec.ERROR
        assert diagnostic.hardware_id == "uav7"
        values = {kv.key: kv.value for kv in diagnostic.values}
        assert values["state"] == "qA"
        assert values["control"] == "fallback"
        assert values["rtt_ms"] == "180.2"
    finally:
        drone.close()
        ros_side.close()


def test_a_paced_camera_image_reaches_ros2_as_the_same_jpeg_with_its_camera_info(
    edge: tuple[Path, int],
) -> None:
    config_path, port = edge
    config = load_config(config_path)
    rng = np.random.default_rng(7)
    image = rng.integers(0, 255, size=(120, 160, 3), dtype=np.uint8)
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    jpeg = encoded.tobytes()
    half = len(jpeg) // 2
    got: queue.Queue[zenoh.Sample] = queue.Queue()
    info_got: queue.Queue[zenoh.Sample] = queue.Queue()
    ros_side = ros_client(port)
    drone = open_bus(config.zenoh, Role.DRONE, connect=[default_flow_endpoint(config.zenoh)])
    try:
        base = "/fleet/uav7/camera"
        image_key = wire.topic_key(
            0, f"{base}/compressed", codec.COMPRESSED_IMAGE, codec.type_hash(codec.COMPRESSED_IMAGE)
        )
        info_key = wire.topic_key(
            0, f"{base}/camera_info", codec.CAMERA_INFO, codec.type_hash(codec.CAMERA_INFO)
        )
        ros_side.declare_subscriber(image_key, got.put)
        ros_side.declare_subscriber(info_key, info_got.put)
        camera = drone.publisher(keys.uplink("uav7", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
        assert camera.wait_matched(10)
        seq = [0]

        def send_in_two_parts() -> None:
            seq[0] += 1
            for part, payload in enumerate((jpeg[:half], jpeg[half:])):
                camera.put(CameraFrame(
                    uav="uav7", seq=seq[0], stamp_ns=seq[0], kind="rgb", encoding="jpeg", width=160,
                    height=120,
                    intrinsics=(200.0, 201.0, 80.0, 60.0), payload=payload, part=part, parts=2,
                ))  # fmt: skip

        sample = first_sample(got, send_in_two_parts)
        picture = codec.decode(codec.COMPRESSED_IMAGE, sample.payload.to_bytes())
        assert picture.format == "jpeg"
        assert bytes(picture.data) == jpeg  # joined from its parts, passed on as it came
        assert picture.header.frame_id == "uav7/camera_optical"
        wire.Attachment.decode(sample.attachment.to_bytes())
        info = codec.decode(codec.CAMERA_INFO, info_got.get(timeout=10).payload.to_bytes())
        assert (info.width, info.height) == (160, 120)
        assert list(info.k) == [200.0, 0.0, 80.0, 0.0, 201.0, 60.0, 0.0, 0.0, 1.0]
        endpoint = get_topic_info(
            f"{base}/compressed", domain_id=0, router_port=port, timeout=2.0, verbose=True
        )
        assert endpoint is not None
        assert endpoint.publishers[0].qos == "2::,1:,:,:,,"  # best effort, the newest image only
    finally:
        drone.close()
        ros_side.close()


def test_a_ros2_path_reaches_the_drones_planner_and_a_goal_outside_the_arena_is_refused(
    edge: tuple[Path, int],
) -> None:
    """A nav_msgs/Path from the SDK's publisher becomes a MissionRequest on the drone's mission key, in
    NED from where the drone is, re-sent every second; a goal outside the arena is refused with a
    mission/status error and never sent. ROS 2 sees the bridge listening (its subscriber tokens)."""
    from zenoh_ros2_sdk.session import ZenohSession

    config_path, port = edge
    config = load_config(config_path)
    missions: queue.Queue[zenoh.Sample] = queue.Queue()
    statuses: queue.Queue[zenoh.Sample] = queue.Queue()
    ros_side = ros_client(port)
    drone = open_bus(config.zenoh, Role.DRONE, connect=[default_flow_endpoint(config.zenoh)])
    publishers: list[Any] = []
    try:
        ros_side.declare_subscriber(
            keys.downlink("uav8", Downlink.MISSION), missions.put
        )  # the planner's part
        status_key = wire.topic_key(0, "/fleet/uav8/mission/status", codec.DIAGNOSTICS,
                                    codec.type_hash(codec.DIAGNOSTICS))  # fmt: skip
        ros_side.declare_subscriber(status_key, statuses.put)
        state_pub = drone.publisher(keys.uplink("uav8", Flow.DEFAULT, Stream.STATE), Priority.DATA_HIGH)
        assert state_pub.wait_matched(10)
        here = State(uav="uav8", seq=1, stamp_ns=1, pos_m=(1.0, 2.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                     quat=(1.0, 0.0, 0.0, 0.0))  # fmt: skip
        # the bridge declares its subscriber tokens when it hears the drone, before it publishes its pose
        poses: queue.Queue[zenoh.Sample] = queue.Queue()
        pose_key = wire.topic_key(0, "/fleet/uav8/pose", codec.POSE, codec.type_hash(codec.POSE))
        ros_side.declare_subscriber(pose_key, poses.put)
        first_sample(poses, lambda: state_pub.put(here))
        listed = dict(get_topic_names_and_types(domain_id=0, router_port=port, timeout=2.0))
        assert listed["/fleet/uav8/mission"] == [codec.PATH]
        assert listed["/fleet/uav8/goal"] == [codec.POSE]
        info = get_topic_info("/fleet/uav8/mission", domain_id=0, router_port=port, timeout=2.0, verbose=True)
        assert info is not None
        assert [s.node_name for s in info.subscribers] == ["dynqos_edge"]

        path_pub = sdk_publisher(port, "/fleet/uav8/mission", codec.PATH)
        publishers.append(path_pub)
        t = ZenohSession.get_instance("127.0.0.1", port).store.types
        poses = [ros_pose(t, (2.0, 1.0, 1.5)), ros_pose(t, (4.0, 1.0, 2.0))]
        header = poses[0].header
        sample = first_sample(missions, lambda: path_pub.publish(header=header, poses=poses), tries=25)
        request = decode(sample.payload.to_bytes())
        assert isinstance(request, MissionRequest)
        assert request.waypoints_m == ((1.0, 2.0, -1.5), (1.0, 2.0, -1.5), (1.0, 4.0, -2.0))
        ok = codec.decode(codec.DIAGNOSTICS, statuses.get(timeout=5).payload.to_bytes()).status[0]
        assert ok.level == codec.OK
        assert f"as mission {request.seq}" in ok.message

        goal_pub = sdk_publisher(port, "/fleet/uav8/goal", codec.POSE)
        publishers.append(goal_pub)
        far = ros_pose(t, (0.0, 500.0, 2.0))
        refusal = first_sample(statuses, lambda: goal_pub.publish(header=far.header, pose=far.pose), tries=25)
        (error,) = codec.decode(codec.DIAGNOSTICS, refusal.payload.to_bytes()).status
        assert error.level == codec.ERROR
        assert "goal refused: waypoint 0 (500.00, 0.00, -2.00) NED is outside the arena" in error.message
        # never sent: what reaches the planner's key from now on is the accepted mission, re-sent
        resent = [decode(missions.get(timeout=3).payload.to_bytes()) for _ in range(2)]
        assert {m.seq for m in resent if isinstance(m, MissionRequest)} == {request.seq}
    finally:
        for publisher in publishers:
            publisher.close()
        drone.close()
        ros_side.close()


def test_detections_and_the_qos_grant_and_decisions_reach_ros2(edge: tuple[Path, int]) -> None:
    """The detector's circles as a vision_msgs/Detection2DArray in the camera's optical frame, the QoS
    agent's grant and the arbiter's decisions as a `qos` DiagnosticArray (edge/ros2/translate.py)."""
    config_path, port = edge
    config = load_config(config_path)
    ros_side = ros_client(port)
    edge_side = open_bus(config.zenoh, Role.EDGE, connect=[default_flow_endpoint(config.zenoh)])
    try:
        got: queue.Queue[zenoh.Sample] = queue.Queue()
        ros_side.declare_subscriber(
            wire.topic_key(0, "/fleet/uav9/detections", codec.DETECTIONS, codec.type_hash(codec.DETECTIONS)),
            got.put,
        )
        found = Detections(uav="uav9", seq=1, frame_seq=7, stamp_ns=1, circles_px=((320.0, 240.0, 30.0),),
                           centers_m=((0.25, -0.1, 2.5, 0.3),))  # fmt: skip
        detections = edge_side.publisher(keys.downlink("uav9", Downlink.DETECTIONS), Priority.DATA)
        assert detections.wait_matched(10)
        sample = first_sample(got, lambda: detections.put(found))
        array = codec.decode(codec.DETECTIONS, sample.payload.to_bytes())
        assert array.header.frame_id == "uav9/camera_optical"
        (detection,) = array.detections
        assert (detection.bbox.center.position.x, detection.bbox.size_x) == (320.0, 60.0)
        p = detection.results[0].pose.pose.position
        assert (p.x, p.y, p.z) == (0.25, -0.1, 2.5)

        qos_key = wire.topic_key(0, "/fleet/uav9/qos", codec.DIAGNOSTICS, codec.type_hash(codec.DIAGNOSTICS))
        ros_side.declare_subscriber(qos_key, got.put)
        grant = edge_side.publisher(keys.downlink("uav9", Downlink.QOS_GRANT), Priority.DATA)
        decision = edge_side.publisher(keys.downlink("uav9", Downlink.QOS_DECISION), Priority.DATA)
        assert grant.wait_matched(10)
        assert decision.wait_matched(10)
        refused = QosGrant(uav="uav9", seq=2, grant=Grant.UNAVAILABLE, backend="camara", session_id="s-1",
                           reason="409 conflict")  # fmt: skip
        (status,) = codec.decode(
            codec.DIAGNOSTICS, first_sample(got, lambda: grant.put(refused)).payload.to_bytes()
        ).status
        assert (status.name, status.level) == ("dynqos/uav9/qos/grant", codec.ERROR)
        assert {kv.key: kv.value for kv in status.values}["session_id"] == "s-1"
        denied = QosDecision(uav="uav9", seq=3, stamp_ns=1, action="deny", reason="budget of 2 held",
                             risk="LR", latency_excess=0.0, holders=("uav1", "uav2"))  # fmt: skip
        decision.put(denied)
        (status,) = codec.decode(codec.DIAGNOSTICS, got.get(timeout=10).payload.to_bytes()).status
        assert status.name == "dynqos/uav9/qos/decision"
        values = {kv.key: kv.value for kv in status.values}
        assert (values["action"], values["holders"]) == ("deny", "uav1 uav2")
    finally:
        edge_side.close()
        ros_side.close()
