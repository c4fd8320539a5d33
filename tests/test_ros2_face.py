"""`dynqos edge ros2` against independent ROS 2 clients over zenoh: the ROBOTIS zenoh-ros2-sdk lists
the drone's topics with their types and hashes as `ros2 topic list -t` would, and a raw zenoh
subscriber on the rmw_zenoh data keys counts every sample, checks its attachment (rmw_zenoh drops a
sample without one) and decodes it with rosbags against what the drone published (docs/ros2.md)."""

from __future__ import annotations

import math
import queue
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh_ros2_sdk import get_topic_info, get_topic_names_and_types

from dynqos.common import keys
from dynqos.common.config import load_config
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import State, SupervisorStatus
from dynqos.common.transport import Priority, Role, default_flow_endpoint, open_bus
from dynqos.edge.ros2 import codec, wire
from tests.conftest import free_tcp_port
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

STATES = 40


@pytest.fixture
def edge(tmp_path: Path) -> Iterator[tuple[Path, int]]:
    port = free_tcp_port()
    config = tmp_path / "edge.toml"
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
    listener = zenoh.Config()
    listener.insert_json5("mode", '"client"')
    listener.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    listener.insert_json5("scouting/multicast/enabled", "false")
    ros_side = zenoh.open(listener)
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
        status = SupervisorStatus(
            uav="uav7", seq=1, stamp_ns=1, state="qA", flow="priority", camera_flow="priority",
            camera_rate_factor=0.5, control_source="fallback", latency="HL", risk="HR", watchdog=True,
            t_cam_ms=None, t_cc_ms=None, spaciousness_m=None, p_cam=0.0, p_cc=0.0, p_lat=0.9, p_cs=0.0,
            prev_state="q2", cause="watchdog", changed_ns=1, rtt_ms=180.25,
        )  # fmt: skip
        # the subscriber to the status topic may not be known to the bridge's publisher, declared with it:
        # the status is sent until one arrives (bounded)
        sample = None
        for _ in range(50):
            status_pub.put(status)
            try:
                sample = got.get(timeout=0.2)
                break
            except queue.Empty:
                continue
        assert sample is not None, "no status reached the ROS 2 side"
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
