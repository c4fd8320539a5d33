"""ROS 2 steers a drone: a `nav_msgs/Path` on `/<prefix>/<uav>/mission` or a `geometry_msgs/PoseStamped`
on `/<prefix>/<uav>/goal` becomes a MissionRequest for that drone's planner replicas, checked as our own
messages are (docs/ros2.md). Pure: bytes and the drone's last position in, a request or a refusal out.

What is checked here, so that the ROS side hears at once why (a `mission/status` DiagnosticArray): the
CDR decodes as the topic's type, the frame is the bridge's `[ros2] frame_id`, every waypoint is finite,
there are not too many, the drone has been heard (its position is the mission's start), and every
waypoint lies in `[planner] arena_min_m..arena_max_m`. The planner checks the arena again and is the
one that decides: a mission it refuses is never flown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dynqos.common.errors import MessageError
from dynqos.common.messages import MAX_MISSION_WAYPOINTS, MissionRequest
from dynqos.edge.planner.missions import outside_arena
from dynqos.edge.ros2 import codec
from dynqos.edge.ros2.wire import Qos, Reliability

Vec = tuple[float, float, float]
STEER_QOS = Qos(Reliability.RELIABLE, depth=10)  # what the subscriber tokens declare
KINDS = {"mission": codec.PATH, "goal": codec.POSE}  # the topic under /<prefix>/<uav>/ -> its ROS type


@dataclass(frozen=True, slots=True)
class Refusal:
    uav: str
    kind: str
    reason: str


class Steering:
    def __init__(self, frame_id: str, arena_min_m: Vec, arena_max_m: Vec) -> None:
        self.frame_id = frame_id
        self.arena = (arena_min_m, arena_max_m)

    def request(
        self, uav: str, kind: str, payload: bytes, position: Vec | None, seq: int, now_ns: int
    ) -> MissionRequest | Refusal:
        """The MissionRequest of one ROS sample on `uav`'s `kind` topic, or why it is refused."""
        try:
            frame, points = self._decode(kind, payload)
        except ValueError as exc:
            return Refusal(uav, kind, str(exc))
        if frame != self.frame_id:
            return Refusal(uav, kind, f"frame {frame!r} is not the bridge's {self.frame_id!r}")
        if not points:
            return Refusal(uav, kind, "no waypoint")
        if len(points) >= MAX_MISSION_WAYPOINTS:
            return Refusal(uav, kind, f"{len(points)} waypoints (at most {MAX_MISSION_WAYPOINTS - 1})")
        if not all(math.isfinite(v) for p in points for v in p):
            return Refusal(uav, kind, "a waypoint is not finite")
        if position is None:
            return Refusal(uav, kind, f"no state from {uav} yet: the mission starts where the drone is")
        why = outside_arena(tuple(points), *self.arena)
        if why is not None:
            return Refusal(uav, kind, why)
        try:
            return MissionRequest(
                uav=uav,
                seq=seq,
                stamp_ns=now_ns,
                waypoints_m=(position, *points),
                source=f"ros2:{kind}",
            )
        except MessageError as exc:
            return Refusal(uav, kind, str(exc))

    @staticmethod
    def _decode(kind: str, payload: bytes) -> tuple[str, list[Vec]]:
        if kind == "mission":
            path = codec.path_waypoints(payload)
            return path.frame, path.points_ned
        goal = codec.pose_goal(payload)
        return goal.frame, goal.points_ned
