"""`dynqos edge ros2`: each drone's pose, odometry, /tf, camera and supervisor status as ROS 2 topics in
rmw_zenoh's format, so that ROS 2 nodes on the same router see them with `ros2 topic list/echo` and no
bridge of their own (docs/ros2.md).

It is an edge client of the router like the other services: it subscribes to the drones' states,
statuses and RGB images (discovering drones as they appear; an image paced in parts is joined first),
and for each drone declares, once, a publisher and a liveliness token per topic under
`/<prefix>/<uav>/`, beside one node token (`/<prefix>/dynqos_edge`).
Every sample carries rmw_zenoh's attachment (sequence from 1, source time, the publisher's GID).

Stamps: a drone stamps its state with its own monotonic clock, which means nothing to ROS; the header
stamp is this service's wall clock when the state arrived. Priority: every ROS-facing sample is
DATA_LOW and dropped rather than queued under congestion, below all of the drone's own traffic.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from dynqos.common import keys
from dynqos.common.config import Config
from dynqos.common.keys import Stream
from dynqos.common.messages import CameraFrame, State, SupervisorStatus
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received, ZenohBus
from dynqos.edge.ros2 import codec, wire
from dynqos.edge.ros2.translate import Translator
from dynqos.edge.ros2.wire import Entity, Node, Qos
from dynqos.edge.service import Service, serve

log = logging.getLogger(__name__)

NODE_NAME = "dynqos_edge"


@dataclass
class Topic:
    """One ROS 2 publisher: its data key, its token (kept alive while declared), its GID and count."""

    name: str
    ros_type: str
    publisher: Any  # zenoh.Publisher
    token: Any  # zenoh.LivelinessToken
    gid: bytes
    sequence: int = 0

    def publish(self, payload: bytes) -> None:
        self.sequence += 1
        attachment = wire.Attachment(self.sequence, time.time_ns(), self.gid).encode()
        self.publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        self.publisher.undeclare()
        self.token.undeclare()


class Ros2Face:
    def __init__(self, config: Config, bus: ZenohBus) -> None:
        self.cfg = config.ros2
        self.session: zenoh.Session = bus.session
        self.queue: BoundedQueue[Received] = BoundedQueue(1024)
        self.stats = [
            bus.subscribe(keys.uplink_all_drones(Stream.STATE), self.queue, expect=(State,)),
            bus.subscribe(keys.uplink_all_drones(Stream.STATUS), self.queue, expect=(SupervisorStatus,)),
            bus.subscribe(keys.uplink_all_drones(Stream.CAMERA_RGB), self.queue, expect=(CameraFrame,)),
        ]
        self.translator = Translator(self.cfg.prefix, self.cfg.frame_id)
        zid = str(self.session.info.zid())
        self.node = Node(self.cfg.domain_id, zid, 0, f"/{self.cfg.prefix}", NODE_NAME)
        self.node_token = self.session.liveliness().declare_token(self.node.token())
        self.topics: dict[str, Topic] = {}
        self.published = 0
        self.service = Service("ros2", self.cfg.health_interval_s)

    def topic(self, name: str, ros_type: str, qos: Qos) -> Topic:
        """The publisher of `name` (a fully qualified topic), declared with its token on first use."""
        found = self.topics.get(name)
        if found is not None:
            return found
        type_hash = codec.type_hash(ros_type)
        token_key = self.node.endpoint_token(
            len(self.topics) + 1, Entity.PUBLISHER, name, ros_type, type_hash, qos
        )
        publisher = self.session.declare_publisher(
            wire.topic_key(self.cfg.domain_id, name, ros_type, type_hash),
            priority=zenoh.Priority.DATA_LOW,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        token = self.session.liveliness().declare_token(token_key)
        topic = Topic(name, ros_type, publisher, token, wire.gid(token_key))
        self.topics[name] = topic
        log.info("ros2: publishing %s (%s)", name, ros_type)
        return topic

    def handle(self, item: Received) -> None:
        uav = keys.parse(item.key).uav
        for sample in self.translator.translate(uav, item.message, time.time_ns()):
            self.topic(sample.topic, sample.ros_type, sample.qos).publish(sample.payload)
            self.published += 1

    def health(self) -> str:
        received = sum(s.received for s in self.stats)
        return f"topics={len(self.topics)} published={self.published} received={received}"

    def run(self) -> None:
        try:
            while not self.service.stop.is_set():
                item = self.queue.get(timeout_s=0.1)
                if item is not None:
                    self.handle(item)
                self.service.maybe_health(self.health)
        finally:
            for topic in self.topics.values():
                topic.close()
            self.node_token.undeclare()  # type: ignore[no-untyped-call]


def _register(worker: Any, metrics: Any) -> None:
    """No metrics of its own yet beyond the process's (health, CPU, memory)."""


def run(config: Config, *, health_file: Path | None = None) -> int:
    def make(cfg: Config, bus: Any) -> Ros2Face:
        return Ros2Face(cfg, bus)

    return serve("ros2", config, make, _register, health_file=health_file)
