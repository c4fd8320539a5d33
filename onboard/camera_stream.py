"""The camera pipeline of the onboard daemon: grab, encode, pace and publish RGB-D on its own threads.

It runs beside the 50 Hz control loop so that rendering or encoding an image never delays a setpoint.
The control loop steers it through `CameraControl` (the flow and the rate the supervisor chose) and
learns from it through two bounded queues: every image handed to the bus (`FrameSent`, which the
onboard core needs before an ack for it can be matched) and the spaciousness of each depth image.

Capture and sending are two threads with one frame between them. Paced, a frame takes most of the
camera's period to hand over (the pace is what the bearer drains), and one thread doing both spent the
grab and the encoding on top of that: at scale 3 a flight's 150 kB frames left it at 13.5 of its
15 frames/s on an idle cell. The sender paces one frame while the next is captured and encoded; when the
link is slower than the camera, a frame not yet sent gives way to the newer one.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Protocol

from dynqos.common.bus import Publisher
from dynqos.common.camera import CameraSource, Pose, RawFrame
from dynqos.common.clock import Clock
from dynqos.common.config import OnboardConfig
from dynqos.common.messages import CameraAck, CameraFrame
from dynqos.common.modes import Flow
from dynqos.common.queues import BoundedQueue
from dynqos.onboard.camera import DEPTH_ENCODING, RateController, encode_depth, encode_rgb
from dynqos.onboard.camera_rate import DelayRateControl, PartSent
from dynqos.onboard.fc import FcState
from dynqos.onboard.pacing import FRAME_HEADER_BYTES, Pacer, split
from dynqos.onboard.risk import Spaciousness
from dynqos.onboard.tick import FrameSent

log = logging.getLogger(__name__)

NO_FRAME_WAIT_S = 0.01  # after a grab that gave nothing: no spinning on a camera that stopped


@dataclass
class FlowPublishers:
    """One publisher per flow for a stream, declared up front: switching flows is picking the other."""

    default: Publisher
    priority: Publisher

    def pick(self, flow: Flow) -> Publisher:
        return self.priority if flow is Flow.PRIORITY else self.default

    def close(self) -> None:
        self.default.close()
        self.priority.close()


class PathPublishers:
    """A stream's publishers on each of the drone's paths; `path` (set by the control loop, read by the
    camera's thread: a plain value) picks the path the camera rides (docs/multipath.md)."""

    def __init__(self, by_path: dict[str, FlowPublishers]) -> None:
        self.by_path = by_path
        self.path = next(iter(by_path))

    def pick(self, flow: Flow) -> Publisher:
        return self.by_path.get(self.path, next(iter(self.by_path.values()))).pick(flow)

    def close(self) -> None:
        for publishers in self.by_path.values():
            publishers.close()


@dataclass
class CameraControl:
    """What the control loop tells the camera: written by one thread, read by the other (plain values)."""

    flow: Flow = Flow.DEFAULT
    rate_factor: float = 1.0


class PoseSource(Protocol):
    def __call__(self) -> FcState | None: ...


@dataclass(frozen=True, slots=True)
class EncodedFrame:
    """A captured frame, encoded, waiting for the sender."""

    seq: int
    stamp_ns: int
    raw: RawFrame  # its size and intrinsics
    rgb: bytes
    depth: bytes | None


class CameraStream:
    def __init__(
        self,
        uav: str,
        config: OnboardConfig,
        camera: CameraSource,
        rgb: FlowPublishers | PathPublishers,
        depth: FlowPublishers | PathPublishers,
        *,
        pose: PoseSource,
        clock: Clock,
        stop: threading.Event,
    ) -> None:
        self.uav = uav
        self.config = config
        self.camera = camera
        self.rgb, self.depth = rgb, depth
        self.pose = pose
        self.clock = clock
        self.stop = stop
        self.control = CameraControl()
        self.rate = RateController(config.camera_fps)
        self.pacer = Pacer(config.camera_pace_mbps * 1e6) if config.camera_pace_mbps > 0 else None
        self.sent: BoundedQueue[FrameSent] = BoundedQueue(1024)
        # camera_rate_control = "delay": the edge's acks, handed over by the control loop
        self.feedback = (
            DelayRateControl(
                config.camera_fps,
                floor=config.camera_rate_floor,
                feedback_timeout_s=config.camera_feedback_timeout_s,
                delay_filter=config.camera_delay_filter,
                controller=config.camera_rate_controller,
                queue_target_ms=config.camera_queue_target_ms,
            )
            if config.camera_rate_control == "delay" and config.camera_fps > 0
            else None
        )
        self._feedback_lock = threading.Lock()  # `feedback` hears acks on one thread, sends on the other
        self.acks: BoundedQueue[CameraAck] = BoundedQueue(256)
        self.spaciousness: BoundedQueue[float] = BoundedQueue(8)
        # one frame between capture and sender: a newer frame replaces one not yet taken (`dropped`)
        self.handoff: BoundedQueue[EncodedFrame] = BoundedQueue(1)
        self._risk: Spaciousness | None = None
        self._thread: threading.Thread | None = None
        self._sender: threading.Thread | None = None
        self.grab_failing = False

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="camera", daemon=True)
        self._sender = threading.Thread(target=self._send_loop, name="camera-send", daemon=True)
        self._thread.start()
        self._sender.start()

    def join(self, timeout_s: float) -> None:
        for thread in (self._thread, self._sender):
            if thread is not None:
                thread.join(timeout=timeout_s)

    def _run(self) -> None:
        seq = 0
        while not self.stop.is_set():
            now = self.clock.now_ns()
            self.rate.factor = self._rate_factor(now)
            if not self.rate.due(now):
                self.stop.wait(min(0.1, max(0.001, self.rate.wait_s(now))))  # the camera's frame rate
                continue
            state = self.pose()
            raw = self._grab((state.pos_m, state.quat) if state else None)
            if raw is None:
                self.stop.wait(NO_FRAME_WAIT_S)  # a camera that gives nothing is not asked again at once
                continue
            seq += 1
            none_dropped = self.handoff.dropped == 0  # only this thread puts: said once, at the first drop
            self.handoff.put(self._encode(raw, seq))
            if none_dropped and self.handoff.dropped:
                log.info("camera: the link's pace is slower than the camera: unsent frames give way to newer")

    def _send_loop(self) -> None:
        while not self.stop.is_set():
            frame = self.handoff.get(0.05)  # a short wait: it sees `stop` soon
            if frame is not None:
                self._send_frame(frame)

    def _rate_factor(self, now_ns: int) -> float:
        """The supervisor's rate factor, or under it what the uplink carries (`feedback`)."""
        if self.feedback is None:
            return self.control.rate_factor
        with self._feedback_lock:
            for ack in self.acks.drain():
                self.feedback.acked(ack.frame_seq, ack.kind, ack.arrival_ns, ack.part_arrivals_us, now_ns)
            return self.feedback.factor(self.control.rate_factor, now_ns)

    def _grab(self, pose: Pose | None) -> RawFrame | None:
        """The source's next frame; a source that fails (a device unplugged) gives none this time, and
        says so once until it gives frames again. The supervisor learns of it from the depth that stops."""
        try:
            raw = self.camera.grab(pose)
        except Exception as exc:  # a driver's error must not end the camera thread, nor the flight
            if not self.grab_failing:
                log.warning("camera: the source failed: %s", exc)
            self.grab_failing = True
            return None
        if raw is not None and self.grab_failing:
            log.info("camera: the source gives frames again")
            self.grab_failing = False
        return raw

    def _encode(self, raw: RawFrame, seq: int) -> EncodedFrame:
        """Stamped when the camera captured it where the source knows (onboard/frame_time.py), else now:
        the camera latency the supervisor measures runs from that stamp to the detector's ack. Its depth's
        spaciousness goes to the control loop from here, whether or not the frame is sent."""
        now = self.clock.now_ns()
        stamp = now if raw.captured_ns is None else min(raw.captured_ns, now)
        rgb = encode_rgb(raw.rgb, self.config.jpeg_quality)
        if raw.depth_m is None:
            return EncodedFrame(seq, stamp, raw, rgb, None)
        depth = encode_depth(raw.depth_m)
        if self._risk is None:
            h, w = raw.depth_m.shape[:2]
            self._risk = Spaciousness(w, h, raw.intrinsics, stride=4)
        value = self._risk(raw.depth_m)
        if value is not None:
            self.spaciousness.put(value)
        return EncodedFrame(seq, stamp, raw, rgb, depth)

    def _send_frame(self, frame: EncodedFrame) -> None:
        flow = self.control.flow  # one flow for every part of both halves of the frame
        self._send(self.rgb.pick(flow), frame.seq, frame.stamp_ns, frame.raw, "rgb", "jpeg", frame.rgb)
        if frame.depth is not None:
            self._send(
                self.depth.pick(flow),
                frame.seq,
                frame.stamp_ns,
                frame.raw,
                "depth",
                DEPTH_ENCODING,
                frame.depth,
            )

    def _send(
        self, pub: Publisher, seq: int, stamp: int, raw: RawFrame, kind: str, encoding: str, data: bytes
    ) -> None:
        h, w = raw.rgb.shape[:2]
        self.sent.put(FrameSent(seq, kind, stamp, len(data)))  # before the first part: an ack may follow
        parts = [data] if self.pacer is None else split(data, self.config.camera_part_bytes)
        handed: list[PartSent] = []
        for index, part in enumerate(parts):
            if self.pacer is not None:
                wait_ns = self.pacer.reserve(len(part) + FRAME_HEADER_BYTES, self.clock.now_ns())
                if wait_ns > 0 and self.stop.wait(wait_ns / 1e9):
                    return
            frame = CameraFrame(
                uav=self.uav,
                seq=seq,
                stamp_ns=stamp,
                kind=kind,
                encoding=encoding,
                width=w,
                height=h,
                intrinsics=raw.intrinsics,
                payload=part,
                part=index,
                parts=len(parts),
            )
            handed.append(PartSent(self.clock.now_ns(), len(part) + FRAME_HEADER_BYTES))
            pub.put(frame)
        if self.feedback is not None:
            with self._feedback_lock:
                self.feedback.sent(seq, kind, handed)
