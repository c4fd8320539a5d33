"""`dynqos edge ros2`: each drone's pose, odometry, /tf, camera and supervisor status as ROS 2 topics in
rmw_zenoh's format, so that ROS 2 nodes on the same router see them with `ros2 topic list/echo` and no
bridge of their own, and ROS 2 nodes steer a drone with a Path or a goal (docs/ros2.md).

It is an edge client of the router like the other services: it subscribes to the drones' states,
statuses and RGB images (discovering drones as they appear; an image paced in parts is joined first),
and for each drone declares, once, a publisher and a liveliness token per topic under
`/<prefix>/<uav>/`, beside one node token (`/<prefix>/dynqos_edge`).
Every sample carries rmw_zenoh's attachment (sequence from 1, source time, the publisher's GID).
Per drone it also subscribes (with subscriber tokens) to `mission` (nav_msgs/Path) and `goal`
(geometry_msgs/PoseStamped); each becomes a MissionRequest to the drone's planner replicas (checked in
edge/ros2/steer.py, re-sent every second), and its outcome a `mission/status` DiagnosticArray.

Stamps: a drone stamps its state with its own monotonic clock, which means nothing to ROS; the header
stamp is this service's wall clock when the state arrived. Priority: every ROS-facing sample is
DATA_LOW and dropped rather than queued under congestion, below all of the drone's own traffic.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher, RawBus, Received, Token
from dynqos.common.config import Config
from dynqos.common.errors import KeyExprError
from dynqos.common.floods import worth_logging
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import (
    CameraFrame,
    Detections,
    QosDecision,
    QosGrant,
    State,
    SupervisorStatus,
)
from dynqos.common.queues import BoundedQueue
from dynqos.edge.resend import LatestMissions
from dynqos.edge.ros2 import codec, wire
from dynqos.edge.ros2.steer import KINDS, STEER_QOS, Refusal, Steering, Vec
from dynqos.edge.ros2.translate import STATUS_QOS, Translator
from dynqos.edge.ros2.wire import Entity, Node, Qos
from dynqos.edge.runtime import EdgeCore, Ports, serve

log = logging.getLogger(__name__)

NODE_NAME = "dynqos_edge"
INBOX_SIZE = 16384  # a publish period's arrivals: 100 drones' states, statuses, 1 KB camera parts, 0.1 s


@dataclass
class Topic:
    """One ROS 2 publisher: its data key, its token (kept alive while declared), its GID and count."""

    name: str
    ros_type: str
    publisher: Publisher
    token: Token
    gid: bytes
    sequence: int = 0

    def publish(self, payload: bytes) -> None:
        self.sequence += 1
        attachment = wire.Attachment(self.sequence, time.time_ns(), self.gid).encode()
        self.publisher.put_bytes(payload, attachment)

    def close(self) -> None:
        self.publisher.close()
        self.token.close()


class Ros2Face(EdgeCore):
    name = "ros2"

    def __init__(self, config: Config, ports: Ports) -> None:
        self.cfg = config.ros2
        self.bus = bus = cast(RawBus, ports.bus)  # zenoh's (`serve` opens it) or a MemoryBus
        self.inbox = ports.inbox
        # the arrivals are taken in batches at each publish period (none: as they come)
        self.batch_s = self.cfg.publish_period_s
        self.stats = [
            bus.subscribe(keys.uplink_all_drones(Stream.STATE), self.inbox, expect=(State,)),
            bus.subscribe(keys.uplink_all_drones(Stream.STATUS), self.inbox, expect=(SupervisorStatus,)),
            bus.subscribe(keys.uplink_all_drones(Stream.CAMERA_RGB), self.inbox, expect=(CameraFrame,)),
            bus.subscribe(keys.downlink_all_drones(Downlink.DETECTIONS), self.inbox, expect=(Detections,)),
            bus.subscribe(keys.downlink_all_drones(Downlink.QOS_GRANT), self.inbox, expect=(QosGrant,)),
            bus.subscribe(keys.downlink_all_drones(Downlink.QOS_DECISION), self.inbox, expect=(QosDecision,)),
        ]
        self.translator = Translator(self.cfg.prefix, self.cfg.frame_id)
        self.node = Node(self.cfg.domain_id, bus.zid, 0, f"/{self.cfg.prefix}", NODE_NAME)
        self.node_token = bus.declare_token(self.node.token())
        self.topics: dict[str, Topic] = {}
        self.entities = 0
        self.published = 0
        self.health_interval_s = self.cfg.health_interval_s
        self._init_steering(config, bus)

    def _init_steering(self, config: Config, bus: RawBus) -> None:
        planner = config.planner
        self.steering = Steering(self.cfg.frame_id, planner.arena_min_m, planner.arena_max_m)
        self.positions: dict[str, Vec] = {}  # each drone's last position: where a mission starts
        self.steered: dict[str, list[Token]] = {}  # each drone's subscriber tokens
        self.steer_queue: BoundedQueue[tuple[str, bytes]] = BoundedQueue(64)
        self.missions = LatestMissions(time.monotonic_ns())  # the last sent per drone, re-sent each second
        self.mission_seq = time.time_ns() // 1_000_000  # newer than a restarted bridge's last
        self.missions_sent = 0
        self.missions_refused = 0
        self._topic_root = f"{self.cfg.domain_id}/{self.cfg.prefix}/"
        for kind, ros_type in KINDS.items():
            bus.raw_subscribe(
                wire.topic_key(
                    self.cfg.domain_id, f"/{self.cfg.prefix}/*/{kind}", ros_type, codec.type_hash(ros_type)
                ),
                lambda key, payload: self.steer_queue.put((key, payload)),
            )

    def _entity(self) -> int:
        self.entities += 1
        return self.entities

    def topic(self, name: str, ros_type: str, qos: Qos) -> Topic:
        """The publisher of `name` (a fully qualified topic), declared with its token on first use."""
        found = self.topics.get(name)
        if found is not None:
            return found
        type_hash = codec.type_hash(ros_type)
        token_key = self.node.endpoint_token(self._entity(), Entity.PUBLISHER, name, ros_type, type_hash, qos)
        publisher = self.bus.publisher(
            wire.topic_key(self.cfg.domain_id, name, ros_type, type_hash),
            Priority.DATA_LOW,
            drop_when_congested=True,
        )
        token = self.bus.declare_token(token_key)
        topic = Topic(name, ros_type, publisher, token, wire.gid(token_key))
        self.topics[name] = topic
        log.info("ros2: publishing %s (%s)", name, ros_type)
        return topic

    def translate(self, item: Received) -> None:
        uav = keys.parse(item.key).uav
        if isinstance(item.message, State):
            self.positions[uav] = item.message.pos_m
            if uav not in self.steered:
                self._listen_for_steering(uav)
        for sample in self.translator.translate(uav, item.message, time.time_ns()):
            self.topic(sample.topic, sample.ros_type, sample.qos).publish(sample.payload)
            self.published += 1

    def _listen_for_steering(self, uav: str) -> None:
        """Subscriber tokens for the drone's mission and goal: ROS 2 sees who listens there."""
        self.steered[uav] = [
            self.bus.declare_token(
                self.node.endpoint_token(
                    self._entity(),
                    Entity.SUBSCRIPTION,
                    f"/{self.cfg.prefix}/{uav}/{kind}",
                    ros_type,
                    codec.type_hash(ros_type),
                    STEER_QOS,
                )
            )
            for kind, ros_type in KINDS.items()
        ]
        log.info("ros2: listening for %s's mission and goal", uav)

    def steer(self, key: str, payload: bytes) -> None:
        """One ROS 2 sample on a drone's mission or goal: a MissionRequest to its planners, or refused."""
        uav, kind = key.removeprefix(self._topic_root).split("/", 2)[:2]
        try:
            keys.check_uav_id(uav)
        except KeyExprError as exc:
            self._refused(Refusal("", kind, str(exc)))
            return
        self.mission_seq += 1
        result = self.steering.request(
            uav, kind, payload, self.positions.get(uav), self.mission_seq, time.monotonic_ns()
        )
        if isinstance(result, Refusal):
            self._refused(result)
            return
        publisher = self.missions.publisher(uav) or self.bus.publisher(
            keys.downlink(uav, Downlink.MISSION), Priority.DATA
        )
        self.missions.send(result, publisher, time.monotonic_ns())
        self.missions_sent += 1
        count = len(result.waypoints_m) - 1
        log.info(
            "ros2: %s for %s sent to its planner as mission %d (%d waypoints)", kind, uav, result.seq, count
        )
        self._mission_status(
            uav,
            codec.OK,
            f"{kind} sent to the planner as mission {result.seq}",
            {"seq": str(result.seq), "waypoints": str(count)},
        )

    def _refused(self, refusal: Refusal) -> None:
        self.missions_refused += 1
        if worth_logging(self.missions_refused, every=100):
            log.warning(
                "ros2: refused a %s for %s (%d refused so far), never flown: %s",
                refusal.kind,
                refusal.uav or "an unknown drone",
                self.missions_refused,
                refusal.reason,
            )
        if refusal.uav:
            self._mission_status(refusal.uav, codec.ERROR, f"{refusal.kind} refused: {refusal.reason}", {})

    def _mission_status(self, uav: str, level: int, message: str, values: dict[str, str]) -> None:
        payload = codec.diagnostics(time.time_ns(), f"dynqos/{uav}/mission", uav, level, message, values)
        self.topic(f"/{self.cfg.prefix}/{uav}/mission/status", codec.DIAGNOSTICS, STATUS_QOS).publish(payload)

    def health(self) -> str:
        received = sum(s.received for s in self.stats)
        return (
            f"topics={len(self.topics)} published={self.published} received={received} "
            f"missions={self.missions_sent} refused={self.missions_refused}"
        )

    def handle(self, events: list[Received], now_ns: int) -> None:
        """What arrived in the last publish period (or each message as it comes), to ROS 2."""
        for item in events:
            self.translate(item)

    def tick(self, now_ns: int) -> float:
        """Missions and goals from ROS 2 since the last tick; the missions re-sent once a second."""
        for key, payload in self.steer_queue.drain():
            self.steer(key, payload)
        self.missions.resend_due(time.monotonic_ns())
        return self.batch_s or 0.1

    async def finish(self) -> None:
        for topic in self.topics.values():
            topic.close()
        for token in (t for tokens in self.steered.values() for t in tokens):
            token.close()
        self.node_token.close()


def _register(worker: Any, metrics: Any) -> None:
    """No metrics of its own yet beyond the process's (health, CPU, memory)."""


def run(config: Config, *, health_file: Path | None = None) -> int:
    return serve("ros2", config, Ros2Face, _register, health_file=health_file, inbox_size=INBOX_SIZE)
