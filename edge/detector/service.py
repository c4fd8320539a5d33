"""`dynqos edge detector`: acknowledges every camera frame at once, then detects circles in the newest.

The ack goes out before any processing (for a paced image, once its last part is in), so the drone
measures the network, not the detector. Frames the detector cannot keep up with are dropped, the
newest kept (one slot per drone and kind). Zenoh callbacks decode each part and join an image's parts
(`PartsJoined`), and queue the whole image into the runtime's inbox (edge/runtime.py); the core acks
on the runtime's loop, and one thread of its own detects.

Several detectors share the drones by drone (best effort, no standby): each holds a liveliness token,
and a drone's frames are acked and searched by the first-ranked live detector only (edge/membership.py,
`LiveSet`); the others drop them unread. When a detector's token goes, its drones move at once.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace

from prometheus_client import Histogram

from dynqos.common import keys
from dynqos.common.builtin_tasks import DETECTOR
from dynqos.common.bus import Priority, Publisher, Received
from dynqos.common.config import Config
from dynqos.common.errors import DecodeError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import CameraAck, CameraFrame, Detections
from dynqos.common.queues import BoundedQueue
from dynqos.common.tasks import Service
from dynqos.edge import metrics
from dynqos.edge.detector.assembler import FrameAssembler
from dynqos.edge.detector.circles import decode_depth, decode_rgb, find_circles, locate
from dynqos.edge.membership import LiveSet, default_replica_id
from dynqos.edge.runtime import EdgeCore, Ports, Runtime

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class WholeFrame(Received):
    """An image whose parts are all in; `arrival_ns` is its last part's, `arrivals_ns` each part's."""

    arrivals_ns: tuple[int, ...] = ()


class PartsJoined(BoundedQueue[Received]):
    """Where the camera subscriptions deliver: each part joins its image on zenoh's thread (the rgb and
    the depth subscriber have one each, so under a lock), and only the whole image goes on into the
    inbox. One wake of the loop per image, not per part: paced at 1 KB, four cameras send 480 parts a
    second, and waking the loop for each cost the detector 19% of a core, joined here 15% (the rest is
    zenoh-python's own hand-off of each part; the same parts in bursts cost 5%; docs/fleet.md)."""

    def __init__(self, assembler: FrameAssembler, inbox: BoundedQueue[Received]) -> None:
        super().__init__(1)  # nothing waits here
        self._assembler = assembler
        self._inbox = inbox
        self._lock = threading.Lock()

    def put(self, item: Received) -> None:
        part = item.message
        if not isinstance(part, CameraFrame):
            return
        with self._lock:
            done = self._assembler.add_timed(part, item.arrival_ns)
        if done is not None:
            frame, arrivals = done
            self._inbox.put(WholeFrame(item.key, frame, item.arrival_ns, item.path, arrivals))


class DetectorService(EdgeCore):
    name = "detector"

    def __init__(self, config: Config, ports: Ports) -> None:
        bus = ports.bus
        self.cfg = config.detector
        self.bus = bus
        self.clock = ports.clock
        self.inbox = ports.inbox
        self.assembler = FrameAssembler()
        parts = PartsJoined(self.assembler, self.inbox)
        self.rgb_stats = bus.subscribe(
            keys.uplink_all_drones(Stream.CAMERA_RGB), parts, expect=(CameraFrame,)
        )
        self.depth_stats = bus.subscribe(
            keys.uplink_all_drones(Stream.CAMERA_DEPTH), parts, expect=(CameraFrame,)
        )
        self.replicas = LiveSet("detector", self.cfg.replica_id or default_replica_id(), bus)
        self._latest: dict[tuple[str, str], Received] = {}
        self._latest_lock = threading.Condition()
        self._ack_pubs: dict[str, Publisher] = {}
        self._det_pubs: dict[str, Publisher] = {}
        self.counters = {
            "frames": 0,
            "acks": 0,
            "detections": 0,
            "dropped": 0,
            "bad_frames": 0,
            "circles": 0,
            "others": 0,  # frames of drones another detector serves
        }
        self.detect_ms: list[float] = []
        self.health_interval_s = self.cfg.health_interval_s
        self.detect_seconds: Histogram | None = None  # set when metrics are on (edge/metrics.py)

    def _publisher(self, table: dict[str, Publisher], uav: str, kind: Downlink, prio: Priority) -> Publisher:
        pub = table.get(uav)
        if pub is None:
            pub = table[uav] = self.bus.publisher(
                keys.downlink(uav, kind), prio, express=kind is Downlink.CAMERA_ACK
            )
        return pub

    def handle(self, events: list[Received], now_ns: int) -> None:
        """Ack every frame that has arrived; hand the newest of each drone and kind to the detector."""
        self.replicas.apply()  # a detector that came or went since: who serves whom now
        for item in events:
            frame = item.message
            if not isinstance(item, WholeFrame) or not isinstance(frame, CameraFrame):
                continue
            if not self.replicas.serves(frame.uav):
                self.counters["others"] += 1
                continue
            arrivals = item.arrivals_ns  # acked now that its last part is in
            self.counters["frames"] += 1
            ack = CameraAck(
                uav=frame.uav,
                seq=frame.seq,
                frame_seq=frame.seq,
                kind=frame.kind,
                stamp_ns=frame.stamp_ns,
                edge_hold_ns=max(0, self.clock.now_ns() - item.arrival_ns),
                arrival_ns=arrivals[0],
                part_arrivals_us=tuple(max(0, t - arrivals[0]) // 1000 for t in arrivals),
            )
            self._publisher(self._ack_pubs, frame.uav, Downlink.CAMERA_ACK, Priority.REAL_TIME).put(ack)
            self.counters["acks"] += 1
            with self._latest_lock:
                if (frame.uav, frame.kind) in self._latest and frame.kind == "rgb":
                    self.counters["dropped"] += 1
                self._latest[(frame.uav, frame.kind)] = item
                self._latest_lock.notify()

    def tick(self, now_ns: int) -> float:
        self.replicas.apply()
        return 0.1

    def detect_next(self, timeout_s: float = 0.1) -> bool:
        with self._latest_lock:
            if not self._latest_lock.wait_for(lambda: any(k[1] == "rgb" for k in self._latest), timeout_s):
                return False
            uav = next(k[0] for k in self._latest if k[1] == "rgb")
            rgb_item = self._latest.pop((uav, "rgb"))
            depth_item = self._latest.get((uav, "depth"))
        frame = rgb_item.message
        assert isinstance(frame, CameraFrame)
        start = time.perf_counter()
        try:
            image = decode_rgb(frame)
            depth = None
            if depth_item is not None:
                depth_frame = depth_item.message
                assert isinstance(depth_frame, CameraFrame)
                if (depth_frame.width, depth_frame.height) == (frame.width, frame.height):
                    depth = decode_depth(depth_frame)
        except DecodeError as exc:
            self.counters["bad_frames"] += 1
            log.warning("detector: %s frame %d: %s", uav, frame.seq, exc)
            return True
        circles = locate(find_circles(image, self.cfg), depth, frame.intrinsics)
        self.detect_ms.append((time.perf_counter() - start) * 1000)
        if self.detect_seconds is not None:
            self.detect_seconds.observe(self.detect_ms[-1] / 1000)
        del self.detect_ms[:-500]
        detections = Detections(
            uav=uav,
            seq=frame.seq,
            frame_seq=frame.seq,
            stamp_ns=frame.stamp_ns,
            circles_px=tuple((c.u_px, c.v_px, c.r_px) for c in circles),
            centers_m=tuple(c.center_m for c in circles),
        )
        self._publisher(self._det_pubs, uav, Downlink.DETECTIONS, Priority.DATA_HIGH).put(detections)
        self.counters["detections"] += 1
        self.counters["circles"] += len(circles)
        return True

    def health(self) -> str:
        ms = sorted(self.detect_ms) or [0.0]
        rejected = self.rgb_stats.rejected + self.depth_stats.rejected
        counts = " ".join(f"{k}={v}" for k, v in self.counters.items())
        parts = f"incomplete={self.assembler.incomplete} inconsistent={self.assembler.inconsistent}"
        replicas = f"replica={self.replicas.me} replicas={len(self.replicas.members)}"
        return f"{counts} {parts} rejected={rejected} detect_ms_p50={ms[len(ms) // 2]:.1f} {replicas}"

    async def start(self, runtime: Runtime) -> None:
        runtime.thread(self.detect_next, "detect")

    async def finish(self) -> None:
        self.replicas.close()


def _make(config: Config, ports: Ports, replica: str) -> DetectorService:
    if replica:  # --replica-id over [detector] replica_id
        config = replace(config, detector=replace(config.detector, replica_id=replica))
    return DetectorService(config, ports)


# `dynqos edge detector` is `dynqos edge serve dynqos.edge.detector.service:SERVICE` (edge/tasks.py).
SERVICE = Service(DETECTOR, make=_make, name="detector", metrics=metrics.detector)
