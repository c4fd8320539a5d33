"""A ROS 2 client nobody here wrote, for the tests: a raw zenoh session on rmw_zenoh's keys, and the
ROBOTIS zenoh-ros2-sdk's publisher given the message definitions it would fetch with git."""

from __future__ import annotations

import queue
from collections.abc import Callable
from typing import Any

import zenoh

from dynqos.edge.ros2 import codec


def ros_client(port: int, wait_s: float = 0.0) -> zenoh.Session:
    """A bare zenoh client of the router: the ROS 2 side, reading the rmw_zenoh keys directly. With
    `wait_s`, zenoh itself keeps trying to reach a router that is still starting, that long."""
    listener = zenoh.Config()
    listener.insert_json5("mode", '"client"')
    listener.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    listener.insert_json5("scouting/multicast/enabled", "false")
    if wait_s:
        listener.insert_json5("connect/timeout_ms", str(round(wait_s * 1000)))
    return zenoh.open(listener)


def first_sample(got: queue.Queue[zenoh.Sample], send: Callable[[], None], tries: int = 50) -> zenoh.Sample:
    """Send (`send()`) until a sample arrives: the bridge declares a topic's publisher on the first
    message, and a subscriber it has not yet heard of can miss that one (bounded: `tries` x 0.2 s)."""
    for _ in range(tries):
        send()
        try:
            return got.get(timeout=0.2)
        except queue.Empty:
            continue
    raise AssertionError("nothing reached the ROS 2 side")


STEER_TYPES = (  # what a Path and a goal are made of, from rosbags' Jazzy definitions
    "builtin_interfaces/msg/Time", "std_msgs/msg/Header", "geometry_msgs/msg/Point",
    "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Pose",
)  # fmt: skip
DEFINITIONS = {
    codec.PATH: "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    codec.POSE: "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
}


def sdk_publisher(port: int, topic: str, ros_type: str) -> Any:
    """The ROBOTIS SDK's ROS 2 publisher (its keys, attachment and tokens), given the definitions it would
    fetch with git: the parts from rosbags' Jazzy store, the type itself as .msg text."""
    from zenoh_ros2_sdk import ROS2Publisher
    from zenoh_ros2_sdk.session import ZenohSession

    store = ZenohSession.get_instance("127.0.0.1", port).store
    store.register({name: codec.STORE.fielddefs[name] for name in STEER_TYPES if name not in store.types})
    if ros_type == codec.PATH and codec.POSE not in store.types:
        sdk_publisher(port, "/unused", codec.POSE).close()  # registers the PoseStamped a Path holds
    return ROS2Publisher(
        topic, ros_type, msg_definition=DEFINITIONS[ros_type], node_name="ground", router_port=port,
        type_hash=codec.type_hash(ros_type),
    )  # fmt: skip


def ros_pose(t: Any, enu: tuple[float, float, float]) -> Any:
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"
    )
    point = t["geometry_msgs/msg/Point"](x=enu[0], y=enu[1], z=enu[2])
    level = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    return t[codec.POSE](header=header, pose=t["geometry_msgs/msg/Pose"](position=point, orientation=level))
