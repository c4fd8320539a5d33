"""vision_msgs (ROS 2 Jazzy's 4.1.1, Apache-2.0), the standard ROS type for detections, which rosbags'
built-in Jazzy store does not carry: its definitions (types and names, as in the package's .msg files)
are registered into our store, so CDR and the RIHS01 hash come from rosbags like every other type's.
tests/test_ros2_wire.py checks the hash against the one zenoh-ros2-sdk computes from the same text.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys import get_types_from_msg

DETECTIONS = "vision_msgs/msg/Detection2DArray"
CLASS_ID = "circle"  # what the detector finds (edge/detector/circles.py)

DEFINITIONS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox2D bbox\nstring id\n"
    ),
    DETECTIONS: "std_msgs/Header header\nDetection2D[] detections\n",
}


def register(store: Any) -> None:
    """Add vision_msgs to a rosbags type store (once)."""
    if DETECTIONS in store.types:
        return
    types: dict[str, Any] = {}
    for name, text in DEFINITIONS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)


def detection_array(
    store: Any,
    header: Any,
    circles_px: tuple[tuple[float, float, float], ...],
    centers_m: tuple[tuple[float, float, float, float] | None, ...],
) -> Any:
    """One Detection2D per circle: its box in pixels (centre, 2r x 2r), the class `circle` with score 1,
    and where depth gave it, its 3-D centre in the camera's optical frame as the hypothesis' pose."""
    t = store.types
    detections = []
    for index, ((u, v, r), center) in enumerate(zip(circles_px, centers_m, strict=True)):
        x, y, z = center[:3] if center is not None else (0.0, 0.0, 0.0)
        pose = t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=np.zeros(36),
        )
        hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id=CLASS_ID, score=1.0), pose=pose
        )
        box = t["vision_msgs/msg/BoundingBox2D"](
            center=t["vision_msgs/msg/Pose2D"](position=t["vision_msgs/msg/Point2D"](x=u, y=v), theta=0.0),
            size_x=2 * r,
            size_y=2 * r,
        )
        detections.append(
            t["vision_msgs/msg/Detection2D"](
                header=header, results=[hypothesis] if center is not None else [], bbox=box, id=str(index)
            )
        )
    return t[DETECTIONS](header=header, detections=detections)
