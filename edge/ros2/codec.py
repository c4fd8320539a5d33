"""ROS 2 messages from dynqos's and back: CDR and RIHS01 type hashes from rosbags, not written here.

Why rosbags: it is maintained, pure Python, carries the message definitions of the ROS 2 distributions
(Jazzy here) so nothing of ROS need be installed, and it computes the RIHS01 hash of each type (REP
2011) as ROS does; its CDR is what `ros2 bag` tools read.

Frames (REP 103/105): dynqos flies in NED with a body frame FRD (as PX4 does); ROS wants ENU and FLU.
A position (n, e, d) is (e, n, -d) in ENU; an attitude q (FRD in NED) is q_enu_ned * q * q_frd_flu,
as PX4's ROS 2 frame transforms do. Pure: bytes in, bytes out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from dynqos.edge.ros2 import vision

Quat = tuple[float, float, float, float]  # w, x, y, z
Vec = tuple[float, float, float]

STORE = get_typestore(Stores.ROS2_JAZZY)
vision.register(STORE)  # vision_msgs, for the detections

POSE = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
PATH = "nav_msgs/msg/Path"
TF = "tf2_msgs/msg/TFMessage"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
DIAGNOSTICS = "diagnostic_msgs/msg/DiagnosticArray"
DETECTIONS = vision.DETECTIONS
OK, WARN, ERROR = 0, 1, 2  # diagnostic_msgs/DiagnosticStatus levels


@cache
def type_hash(ros_type: str) -> str:
    """`RIHS01_<64 hex>` of a message type of the store."""
    return str(STORE.hash_rihs01(ros_type))


def _qmul(a: Quat, b: Quat) -> Quat:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


_H = math.sqrt(0.5)
Q_ENU_NED: Quat = (0.0, _H, _H, 0.0)  # the rotation taking NED axes to ENU: x<->y, z flipped
Q_FRD_FLU: Quat = (0.0, 1.0, 0.0, 0.0)  # 180 degrees about x: y and z flipped


def enu_of_ned(v: Vec) -> Vec:
    return (v[1], v[0], -v[2])


def ned_of_enu(v: Vec) -> Vec:
    return (v[1], v[0], -v[2])


def flu_enu_of_frd_ned(q: Quat) -> Quat:
    w, x, y, z = _qmul(_qmul(Q_ENU_NED, q), Q_FRD_FLU)
    return (w, x, y, z) if w >= 0 else (-w, -x, -y, -z)  # one of the two equal quaternions


def _time(stamp_ns: int) -> Any:
    return STORE.types["builtin_interfaces/msg/Time"](
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
    )


def _header(stamp_ns: int, frame: str) -> Any:
    return STORE.types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame)


def _pose(pos_ned: Vec, quat_frd_ned: Quat) -> Any:
    t = STORE.types
    x, y, z = enu_of_ned(pos_ned)
    w, qx, qy, qz = flu_enu_of_frd_ned(quat_frd_ned)
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=w),
    )


def encode(message: Any) -> bytes:
    """CDR, little endian, with its 4-byte header, as rmw_zenoh publishes."""
    return bytes(STORE.serialize_cdr(message, message.__msgtype__))


def decode(ros_type: str, data: bytes) -> Any:
    return STORE.deserialize_cdr(data, ros_type)


def pose_stamped(stamp_ns: int, frame: str, pos_ned: Vec, quat_frd_ned: Quat) -> bytes:
    return encode(STORE.types[POSE](header=_header(stamp_ns, frame), pose=_pose(pos_ned, quat_frd_ned)))


def odometry(
    stamp_ns: int, frame: str, child_frame: str, pos_ned: Vec, vel_ned: Vec, quat_frd_ned: Quat
) -> bytes:
    """The twist in the child (body, FLU) frame, as REP 105 and nav_msgs/Odometry say."""
    t = STORE.types
    q = flu_enu_of_frd_ned(quat_frd_ned)
    v_body = _rotate(_conj(q), enu_of_ned(vel_ned))
    unknown = np.zeros(36, dtype=np.float64)  # no covariance is estimated
    twist = t["geometry_msgs/msg/Twist"](
        linear=t["geometry_msgs/msg/Vector3"](x=v_body[0], y=v_body[1], z=v_body[2]),
        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return encode(
        t[ODOMETRY](
            header=_header(stamp_ns, frame),
            child_frame_id=child_frame,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=_pose(pos_ned, quat_frd_ned), covariance=unknown
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=unknown.copy()),
        )
    )


def _conj(q: Quat) -> Quat:
    return (q[0], -q[1], -q[2], -q[3])


def _rotate(q: Quat, v: Vec) -> Vec:
    _, x, y, z = _qmul(_qmul(q, (0.0, *v)), _conj(q))
    return (x, y, z)


@dataclass(frozen=True, slots=True)
class Waypoints:
    frame: str
    points_ned: list[Vec]


def path_waypoints(data: bytes) -> Waypoints:
    """The positions of a nav_msgs/Path, in NED; ValueError for bytes that are not one."""
    try:
        path = decode(PATH, data)
    except Exception as exc:  # rosbags raises several kinds for truncated or foreign bytes
        raise ValueError(f"not a {PATH} in CDR: {exc}") from None
    points = [ned_of_enu((p.pose.position.x, p.pose.position.y, p.pose.position.z)) for p in path.poses]
    return Waypoints(str(path.header.frame_id), points)


def pose_goal(data: bytes) -> Waypoints:
    """The position of a geometry_msgs/PoseStamped (a goal), in NED; ValueError for bytes that are not
    one. Its orientation is not used: the planner flies yaw along the way."""
    try:
        pose = decode(POSE, data)
    except Exception as exc:  # rosbags raises several kinds for truncated or foreign bytes
        raise ValueError(f"not a {POSE} in CDR: {exc}") from None
    p = pose.pose.position
    return Waypoints(str(pose.header.frame_id), [ned_of_enu((p.x, p.y, p.z))])


def transform(stamp_ns: int, frame: str, child_frame: str, pos_ned: Vec, quat_frd_ned: Quat) -> bytes:
    """A tf2_msgs/TFMessage with the one transform frame -> child_frame (the drone's body, FLU)."""
    t = STORE.types
    x, y, z = enu_of_ned(pos_ned)
    w, qx, qy, qz = flu_enu_of_frd_ned(quat_frd_ned)
    stamped = t["geometry_msgs/msg/TransformStamped"](
        header=_header(stamp_ns, frame),
        child_frame_id=child_frame,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=w),
        ),
    )
    return encode(t[TF](transforms=[stamped]))


def diagnostics(
    stamp_ns: int, name: str, hardware_id: str, level: int, message: str, values: dict[str, str]
) -> bytes:
    """One diagnostic_msgs/DiagnosticStatus in a DiagnosticArray (what rqt_robot_monitor shows)."""
    t = STORE.types
    status = t["diagnostic_msgs/msg/DiagnosticStatus"](
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in values.items()],
    )
    return encode(t[DIAGNOSTICS](header=_header(stamp_ns, ""), status=[status]))


def compressed_image(stamp_ns: int, frame: str, image_format: str, data: bytes) -> bytes:
    """The encoded image as it came (JPEG), not decoded and encoded again."""
    message = STORE.types[COMPRESSED_IMAGE](
        header=_header(stamp_ns, frame), format=image_format, data=np.frombuffer(data, dtype=np.uint8)
    )
    return encode(message)


def camera_info(
    stamp_ns: int, frame: str, width: int, height: int, intrinsics: tuple[float, float, float, float]
) -> bytes:
    """A pinhole camera without distortion (what the drone reports: fx, fy, cx, cy)."""
    fx, fy, cx, cy = intrinsics
    t = STORE.types
    message = t[CAMERA_INFO](
        header=_header(stamp_ns, frame),
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=np.zeros(5),
        k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64),
        r=np.eye(3).ravel(),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64),
        binning_x=0,
        binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )
    return encode(message)


def detections(
    stamp_ns: int,
    frame: str,
    circles_px: tuple[tuple[float, float, float], ...],
    centers_m: tuple[tuple[float, float, float, float] | None, ...],
) -> bytes:
    """The detector's circles in one frame as a vision_msgs/Detection2DArray (edge/ros2/vision.py)."""
    return encode(vision.detection_array(STORE, _header(stamp_ns, frame), circles_px, centers_m))
