"""The rmw_zenoh wire format (edge/ros2/wire.py) and the ROS 2 messages (edge/ros2/codec.py), checked
against implementations nobody here wrote: zenoh's own serializer for the attachment, the ROBOTIS
zenoh-ros2-sdk's key, token, QoS and type-hash code, and rmw_zenoh_cpp's rules as its source states
them (liveliness_utils.cpp `qos_to_keyexpr`, qos.cpp's defaults) (docs/ros2.md)."""

from __future__ import annotations

import math

import pytest
from zenoh.ext import Int64, z_serialize
from zenoh_ros2_sdk import keyexpr as sdk_keys
from zenoh_ros2_sdk import qos as sdk_qos
from zenoh_ros2_sdk import utils as sdk_utils
from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment
from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity

from dynqos.edge.ros2 import codec, vision, wire
from dynqos.edge.ros2.wire import Attachment, Durability, Entity, Node, Qos, Reliability

POSE_HASH = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"  # Jazzy's

# The standard definitions (common_interfaces, rcl_interfaces; Jazzy), for the SDK's own RIHS01 code.
DEFINITIONS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
}


def test_the_data_key_is_domain_topic_dds_type_and_hash_as_the_sdk_builds_it() -> None:
    key = wire.topic_key(0, "/dynqos/uav1/pose", codec.POSE, codec.type_hash(codec.POSE))
    assert key == f"0/dynqos/uav1/pose/geometry_msgs::msg::dds_::PoseStamped_/{POSE_HASH}"
    assert key == sdk_keys.topic_keyexpr(
        0, "/dynqos/uav1/pose", sdk_utils.ros2_to_dds_type(codec.POSE), POSE_HASH
    )
    with pytest.raises(ValueError, match="not a ROS 2 message type"):
        wire.dds_type_name("geometry_msgs/PoseStamped")


def test_the_type_hash_is_the_one_the_sdk_computes_from_the_definitions() -> None:
    deps = {k: v for k, v in DEFINITIONS.items()}
    ours = codec.type_hash(codec.POSE)
    theirs = sdk_utils.get_type_hash(
        codec.POSE, msg_definition="std_msgs/Header header\nPose pose\n", dependencies=deps
    )
    assert ours == theirs == POSE_HASH


def test_tokens_match_the_sdks_node_and_publisher_tokens() -> None:
    node = Node(domain_id=0, zid="aa11", node_id=3, namespace="/dynqos", name="uav1")
    assert node.token() == "@ros2_lv/0/aa11/3/3/NN/%/%dynqos/uav1"
    sdk_node = NodeEntity(
        domain_id=0, session_id="aa11", node_id=3, node_name="uav1", namespace="/dynqos", enclave="%"
    )
    assert node.token() == sdk_keys.node_liveliness_keyexpr(sdk_node)
    qos = Qos(Reliability.BEST_EFFORT, depth=1)
    token = node.endpoint_token(7, Entity.PUBLISHER, "/dynqos/uav1/pose", codec.POSE, POSE_HASH, qos)
    sdk_endpoint = EndpointEntity(
        node=sdk_node, entity_id=7, kind=EntityKind.PUBLISHER, name="/dynqos/uav1/pose",
        dds_type_name=sdk_utils.ros2_to_dds_type(codec.POSE), type_hash=POSE_HASH, qos=qos.token_field(),
    )  # fmt: skip
    assert token == sdk_keys.endpoint_liveliness_keyexpr(sdk_endpoint)
    assert token.endswith(
        f"/%dynqos%uav1%pose/geometry_msgs::msg::dds_::PoseStamped_/{POSE_HASH}/2::,1:,:,:,,"
    )


@pytest.mark.parametrize(
    ("qos", "field"),
    [
        (Qos(), "::,:,:,:,,"),  # rmw_zenoh's defaults: every value left out
        (Qos(depth=10), "::,10:,:,:,,"),  # the ROS 2 default profile's depth
        (Qos(Reliability.BEST_EFFORT, depth=1), "2::,1:,:,:,,"),
        (Qos(durability=Durability.TRANSIENT_LOCAL, depth=1), ":1:,1:,:,:,,"),
    ],
)
def test_the_qos_field_leaves_out_rmw_zenohs_defaults_and_the_sdk_reads_it(qos: Qos, field: str) -> None:
    assert qos.token_field() == field
    read = sdk_qos.QosProfile.decode(field)
    assert read.reliability.value == int(qos.reliability)
    assert read.durability.value == int(qos.durability)
    if qos.depth != wire.DEFAULT_DEPTH:
        assert read.history_depth == qos.depth


def test_the_attachment_is_what_zenohs_serializer_and_the_sdk_make_of_it() -> None:
    gid = wire.gid("@ros2_lv/0/aa11/3/7/MP/%/%dynqos/uav1/%dynqos%uav1%pose")
    attachment = Attachment(sequence=5, source_ns=1_795_000_000_123_456_789, gid=gid)
    data = attachment.encode()
    assert len(data) == 33
    assert data == z_serialize((Int64(5), Int64(1_795_000_000_123_456_789), gid)).to_bytes()
    theirs = SdkAttachment.from_bytes(data)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (5, 1_795_000_000_123_456_789, gid)
    assert Attachment.decode(data) == attachment
    for bad in (data[:-1], data[:16] + b"\x08" + data[17:]):
        with pytest.raises(ValueError, match="attachment"):
            Attachment.decode(bad)


def _yaw_enu(q: tuple[float, float, float, float]) -> float:
    w, x, y, z = q
    return math.degrees(math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def test_a_pose_in_ned_frd_reads_in_enu_flu_through_rosbags() -> None:
    h = math.sqrt(0.5)
    east_facing = (h, 0.0, 0.0, h)  # yaw +90 degrees in NED: the nose to the east
    data = codec.pose_stamped(1_795_000_000_250_000_000, "map", (1.0, 2.0, -3.0), east_facing)
    assert data[:4] == wire.CDR_LE_HEADER
    pose = codec.decode(codec.POSE, data)
    assert (pose.header.stamp.sec, pose.header.stamp.nanosec) == (1_795_000_000, 250_000_000)
    assert pose.header.frame_id == "map"
    p = pose.pose.position
    assert (p.x, p.y, p.z) == (2.0, 1.0, 3.0)  # east, north, up
    o = pose.pose.orientation
    assert _yaw_enu((o.w, o.x, o.y, o.z)) == pytest.approx(0.0, abs=1e-9)  # facing east: ENU yaw 0
    north = codec.decode(codec.POSE, codec.pose_stamped(0, "map", (0, 0, 0), (1.0, 0.0, 0.0, 0.0)))
    o = north.pose.orientation
    assert _yaw_enu((o.w, o.x, o.y, o.z)) == pytest.approx(90.0)
    assert (o.x, o.y) == pytest.approx((0.0, 0.0))  # level stays level: no roll, no pitch


def test_odometry_gives_the_velocity_in_the_body_frame() -> None:
    h = math.sqrt(0.5)
    # flying north at 2 m/s, climbing at 0.5 m/s, nose to the east: body left is north
    data = codec.odometry(0, "map", "uav1/base_link", (0, 0, -2), (2.0, 0.0, -0.5), (h, 0.0, 0.0, h))
    odom = codec.decode(codec.ODOMETRY, data)
    assert odom.child_frame_id == "uav1/base_link"
    v = odom.twist.twist.linear
    assert (v.x, v.y, v.z) == pytest.approx((0.0, 2.0, 0.5))
    assert odom.pose.pose.position.z == pytest.approx(2.0)


def test_a_path_gives_its_waypoints_in_ned_and_junk_is_a_clear_error() -> None:
    t = codec.STORE.types
    zero = t["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = t["std_msgs/msg/Header"](stamp=zero, frame_id="map")
    level = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    point = t["geometry_msgs/msg/Point"]
    poses = [
        t[codec.POSE](
            header=header,
            pose=t["geometry_msgs/msg/Pose"](position=point(x=e, y=n, z=u), orientation=level),
        )
        for e, n, u in ((1.0, 0.0, 2.5), (1.0, 3.0, 2.5))
    ]
    data = codec.encode(t[codec.PATH](header=header, poses=poses))
    got = codec.path_waypoints(data)
    assert got.frame == "map"
    assert got.points_ned == [(0.0, 1.0, -2.5), (3.0, 1.0, -2.5)]
    with pytest.raises(ValueError, match="not a nav_msgs/msg/Path"):
        codec.path_waypoints(data[:20])


def test_the_detections_type_hash_is_the_one_the_sdk_computes_from_vision_msgs_definitions() -> None:
    """vision_msgs is not in rosbags' Jazzy store: ours registers its 4.1.1 definitions, and the SDK's own
    RIHS01 code, given the same .msg texts, must arrive at the same hash (what ROS 2 nodes compute)."""
    deps = {
        **DEFINITIONS,
        "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
        **{name: text for name, text in vision.DEFINITIONS.items() if name != vision.DETECTIONS},
    }
    theirs = sdk_utils.get_type_hash(
        vision.DETECTIONS, msg_definition=vision.DEFINITIONS[vision.DETECTIONS], dependencies=deps
    )
    assert codec.type_hash(codec.DETECTIONS) == theirs
    data = codec.detections(5, "uav1/camera_optical", ((320.0, 240.0, 12.0), (10.0, 20.0, 4.0)),
                            ((0.1, -0.2, 3.0, 0.15), None))  # fmt: skip
    array = codec.decode(codec.DETECTIONS, data)
    first, second = array.detections
    assert array.header.frame_id == "uav1/camera_optical"
    assert (first.bbox.center.position.x, first.bbox.center.position.y, first.bbox.size_x) == (
        320.0,
        240.0,
        24.0,
    )
    (hypothesis,) = first.results
    assert (hypothesis.hypothesis.class_id, hypothesis.hypothesis.score) == ("circle", 1.0)
    p = hypothesis.pose.pose.position
    assert (p.x, p.y, p.z) == (0.1, -0.2, 3.0)
    assert second.results == []  # no depth there: a box without a 3-D hypothesis
