"""A camera source that fails mid-flight (a driver error, as when a RealSense is unplugged: no device can
be unplugged here, so a real frame source is made to raise what the driver raises) neither ends the
camera thread nor spins: one line says so, frames stop, and they resume with the source. What the
supervisor then does with the depth that stopped is tests/test_supervisor.py's; the daemon flying on
after a recording ends is tests/test_realsense.py's (docs/onboard.md, "Camera faults")."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority
from dynqos.common.camera import Pose, RawFrame
from dynqos.common.clock import MonotonicClock
from dynqos.common.config import OnboardConfig
from dynqos.common.keys import Flow, Stream
from dynqos.onboard.camera import FilesCamera
from dynqos.onboard.camera_stream import CameraStream, FlowPublishers

pytestmark = [pytest.mark.timeout(60)]


class Unpluggable:
    """The real frames, or the error librealsense raises for a device that is gone."""

    def __init__(self, frames: FilesCamera) -> None:
        self.frames = frames
        self.gone = threading.Event()
        self.failed_grabs = 0

    def grab(self, pose: Pose | None) -> RawFrame | None:
        if self.gone.is_set():
            self.failed_grabs += 1
            raise RuntimeError("No device connected")
        return self.frames.grab(pose)


def test_a_failing_source_is_logged_once_paced_and_followed_again_when_it_returns(
    shared_data: Path, caplog: pytest.LogCaptureFixture
) -> None:
    bus = MemoryBus()
    source = Unpluggable(FilesCamera(shared_data / "rgbd", (518.0, 519.0, 325.5, 253.5)))

    def publishers(stream: Stream) -> FlowPublishers:
        return FlowPublishers(*(bus.publisher(keys.uplink("uav1", flow, stream), Priority.DATA)
                                for flow in (Flow.DEFAULT, Flow.PRIORITY)))  # fmt: skip

    stop = threading.Event()
    stream = CameraStream(
        "uav1", OnboardConfig(camera_fps=20), source, publishers(Stream.CAMERA_RGB),
        publishers(Stream.CAMERA_DEPTH), pose=lambda: None, clock=MonotonicClock(), stop=stop,
    )  # fmt: skip
    caplog.set_level(logging.INFO, logger="dynqos.onboard.camera_stream")
    stream.start()
    try:
        assert stream.sent.get(5.0) is not None  # frames flow
        assert stream.spaciousness.get(5.0) is not None  # and depth with them
        source.gone.set()
        while source.failed_grabs < 20:  # the thread keeps asking, at its own pace
            assert stream._thread is not None
            assert stream._thread.is_alive()
            stop.wait(0.05)  # the failing source has no event to wait on
        stream.sent.drain()
        stream.spaciousness.drain()
        assert stream.sent.get(0.3) is None  # nothing while the device is gone
        source.gone.clear()
        assert stream.sent.get(5.0) is not None  # back with the device
        assert stream.spaciousness.get(5.0) is not None
    finally:
        stop.set()
        stream.join(5.0)
        bus.close()
    messages = [r.getMessage() for r in caplog.records]
    assert messages.count("camera: the source failed: No device connected") == 1  # once, not per grab
    assert "camera: the source gives frames again" in messages
    assert source.failed_grabs < 200  # paced: no spin (20 fps, 10 ms after a failed grab at most)
