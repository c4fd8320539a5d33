"""The camera captures the next frame while the last one is still being paced onto the link, and a frame
the link had no time for gives way to a newer one (onboard/camera_stream.py). One thread doing both
spent the grab on top of the pacing: a flight whose frames took most of the period to pace (scale 3)
kept 13.5 of its 15 frames/s on an idle cell."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dynqos.common.camera import Pose, RawFrame
from dynqos.common.clock import MonotonicClock
from dynqos.common.config import OnboardConfig
from dynqos.common.messages import CameraFrame, Message
from dynqos.onboard.camera import encode_depth, encode_rgb
from dynqos.onboard.camera_stream import CameraStream, EncodedFrame, FlowPublishers
from dynqos.onboard.pacing import FRAME_HEADER_BYTES, split

pytestmark = [pytest.mark.timeout(60)]

FPS = 20.0  # a 50 ms period
GRAB_S = 0.025  # a render that takes half of it
PACE_S = 0.035  # and the link's pace that takes most of it: together more than the period
PART_BYTES = 1024


class Events:
    """Grabs and parts put, in the order they happened, on one clock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.log: list[tuple[str, int, int, int]] = []  # (what, frame seq or -1, part, parts)
        self.frames_done = threading.Semaphore(0)

    def add(self, what: str, seq: int = -1, part: int = 0, parts: int = 0) -> None:
        with self.lock:
            self.log.append((what, seq, part, parts))


class SlowRender:
    def __init__(self, events: Events, frame: RawFrame) -> None:
        self.events, self.frame = events, frame

    def grab(self, pose: Pose | None) -> RawFrame:
        self.events.add("grab")
        time.sleep(GRAB_S)  # the work a render does, not a wait for something
        return self.frame


class Recorder:
    """A publisher that notes each part it is handed."""

    sent = 0
    sent_bytes = 0

    def __init__(self, events: Events, kind: str) -> None:
        self.events, self.kind, self.key = events, kind, f"camera/{kind}"

    def put_bytes(self, data: bytes, attachment: bytes | None = None) -> None:
        raise AssertionError("the camera puts messages")

    def put(self, message: Message) -> None:
        assert isinstance(message, CameraFrame)
        self.events.add(self.kind, message.seq, message.part, message.parts)
        if self.kind == "depth" and message.part == message.parts - 1:
            self.events.frames_done.release()

    def close(self) -> None:
        pass


def _frame() -> RawFrame:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)  # noise: JPEG keeps it large
    depth = rng.uniform(0.5, 8.0, (48, 64)).astype(np.float32)
    return RawFrame(rgb, depth, (50.0, 50.0, 32.0, 24.0))


def _pace_mbps(frame: RawFrame) -> float:
    """The pace at which one frame's parts (both halves) take PACE_S."""
    wire = 0
    for data in (encode_rgb(frame.rgb, 90), encode_depth(frame.depth_m)):
        wire += sum(len(p) + FRAME_HEADER_BYTES for p in split(data, PART_BYTES))
    return wire * 8 / PACE_S / 1e6


def test_the_next_frame_is_captured_while_the_last_is_paced() -> None:
    events, frame = Events(), _frame()
    config = OnboardConfig(camera_fps=FPS, camera_pace_mbps=_pace_mbps(frame), camera_part_bytes=PART_BYTES)
    rgb = FlowPublishers(Recorder(events, "rgb"), Recorder(events, "rgb"))
    depth = FlowPublishers(Recorder(events, "depth"), Recorder(events, "depth"))
    stop = threading.Event()
    stream = CameraStream(
        "uav1",
        config,
        SlowRender(events, frame),
        rgb,
        depth,
        pose=lambda: None,
        clock=MonotonicClock(),
        stop=stop,
    )
    stream.start()
    try:
        for _ in range(6):
            assert events.frames_done.acquire(timeout=10.0)
    finally:
        stop.set()
        stream.join(5.0)
    with events.lock:
        log = list(events.log)
    # A grab between a frame's first part and its last: the sender was still pacing it.
    overlapped = 0
    sending: int | None = None
    for what, seq, part, parts in log:
        if what == "rgb" and part == 0:
            sending = seq
        elif what == "depth" and seq == sending and part == parts - 1:
            sending = None
        elif what == "grab" and sending is not None:
            overlapped += 1
    assert overlapped >= 3, log


def test_a_frame_not_yet_taken_gives_way_to_the_newer_one() -> None:
    events = Events()
    rgb = FlowPublishers(Recorder(events, "rgb"), Recorder(events, "rgb"))
    depth = FlowPublishers(Recorder(events, "depth"), Recorder(events, "depth"))
    stream = CameraStream(
        "uav1",
        OnboardConfig(),
        SlowRender(events, _frame()),
        rgb,
        depth,
        pose=lambda: None,
        clock=MonotonicClock(),
        stop=threading.Event(),
    )  # not started: its hand-off alone
    handoff = stream.handoff
    first = EncodedFrame(1, 10, _frame(), b"a", None)
    second = EncodedFrame(2, 20, _frame(), b"b", None)
    handoff.put(first)
    handoff.put(second)  # the link had no time for the first
    assert handoff.dropped == 1
    assert handoff.get(0.0) is second
    assert handoff.get(0.0) is None  # nothing waits twice
    handoff.put(first)
    assert handoff.dropped == 1
    assert handoff.get(0.0) is first
