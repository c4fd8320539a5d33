"""The RealSense source through real librealsense, no camera: a recording made in the test from the real
RGB-D frames (tests/realsense_recording.py), played back as `[onboard] camera = "realsense"` plays it,
checked against the same frames read directly (docs/onboard.md, "A RealSense depth camera")."""

from __future__ import annotations

import re
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynqos.common import keys
from dynqos.common.camera import RawFrame
from dynqos.common.errors import ConfigError
from dynqos.common.keys import Stream
from dynqos.common.messages import SupervisorStatus
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received
from dynqos.onboard.realsense import RealSenseCamera
from dynqos.onboard.risk import Spaciousness
from dynqos.reports.outcomes import log_times
from tests.procs import DynqosProcess
from tests.realsense_recording import INTRINSICS, record
from tests.test_onboard_loop import Observer, edge_loop

pytestmark = [pytest.mark.timeout(120), pytest.mark.usefixtures("librealsense")]


def _grab_all(camera: RealSenseCamera, expected: int) -> list[RawFrame]:
    """Frames until `expected` came or the recording ended (grab waits at most 100 ms each time)."""
    frames: list[RawFrame] = []
    misses = 0
    while len(frames) < expected and misses < 30:
        frame = camera.grab(None)
        if frame is None:
            misses += 1
        else:
            frames.append(frame)
    return frames


def test_a_recording_plays_back_aligned_with_the_devices_scale_and_intrinsics(
    shared_data: Path, tmp_path: Path
) -> None:
    recording = tmp_path / "rgbd.db3"
    used = record(shared_data / "rgbd", recording, count=10)
    camera = RealSenseCamera(str(recording), 640, 480, 15)
    try:
        frames = _grab_all(camera, len(used))
        assert camera.depth_scale == pytest.approx(0.001)
        assert camera.grab(None) is None  # the recording ended: nothing more, no error
    finally:
        camera.close()
    assert len(frames) >= len(used) - 1, len(frames)  # playback may skip one at its start
    spaciousness = Spaciousness(640, 480, INTRINSICS, stride=4)
    matched = 0
    for frame in frames:
        assert frame.intrinsics == pytest.approx(INTRINSICS)  # the device's, as recorded
        assert frame.depth_m is not None
        # which source frame it is: the colour image is passed through unchanged
        n = next(n for n in set(used) if np.array_equal(frame.rgb, _color(shared_data, n)))
        raw_m = cv2.imread(str(shared_data / "rgbd" / f"depth_{n}.pgm"), cv2.IMREAD_UNCHANGED) * 0.001
        same = np.isclose(frame.depth_m, raw_m, atol=1e-4).mean()
        assert same > 0.95, same  # aligned to colour (same intrinsics here): all but the edges' pixels
        direct, played = spaciousness(raw_m.astype(np.float32)), spaciousness(frame.depth_m)
        assert direct is not None
        assert played == pytest.approx(direct, rel=0.02)  # the risk input is the frames' own
        matched += 1
    assert matched == len(frames)


def test_the_devices_frame_stamps_become_the_capture_time(shared_data: Path, tmp_path: Path) -> None:
    """Each frame's capture time is its device stamp on the daemon's clock (onboard/frame_time.py): the
    offset between the two only ever falls (to the quickest frame's), where the arrival times, which
    jitter both ways by milliseconds, would not; a frame stamped 60 ms late keeps that offset too."""
    recording = tmp_path / "rgbd.db3"
    stamps: list[float] = []
    used = record(shared_data / "rgbd", recording, count=10, lag_ms={5: 60.0}, stamps_ms=stamps)
    camera = RealSenseCamera(str(recording), 640, 480, 15)
    offsets_ms: list[float] = []
    k = -1
    try:
        # to the recording's end: the playback gives some frames twice, and those count in the grabs
        for frame in _grab_all(camera, 2 * len(used)):
            assert frame.captured_ns is not None
            n = next(n for n in set(used) if np.array_equal(frame.rgb, _color(shared_data, n)))
            if k >= 0 and used[k] == n:
                continue  # a frame the playback gave twice (with the next one's depth)
            k = next(j for j in range(k + 1, len(used)) if used[j] == n)  # which recorded frame
            offsets_ms.append(frame.captured_ns / 1e6 - stamps[k])
    finally:
        camera.close()
    assert len(offsets_ms) >= len(used) - 1, offsets_ms
    steps = np.diff(offsets_ms)
    assert (steps <= 0.001).all(), offsets_ms
    assert offsets_ms[0] - offsets_ms[-1] < 30, offsets_ms  # the first frame came about as quickly


def _color(shared_data: Path, n: int) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(shared_data / "rgbd" / f"color_{n}.png")), cv2.COLOR_BGR2RGB)


def test_a_missing_recording_or_device_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such recording"):
        RealSenseCamera(str(tmp_path / "absent.db3"), 640, 480, 15)
    with pytest.raises(ConfigError, match="no RealSense device is connected"):
        RealSenseCamera("", 640, 480, 15)  # this machine has none
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"not a recording")
    with pytest.raises(ConfigError, match="cannot start the RealSense pipeline"):
        RealSenseCamera(str(junk), 640, 480, 15)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_demo_drone_flies_with_its_risk_from_a_realsense_recording(
    shared_data: Path, tmp_path: Path
) -> None:
    """The whole loop with `camera = "realsense"` playing a recording of the real frames through
    librealsense (10 s at 5 fps, the daemon's camera rate here), then the recording's end: every
    spaciousness the supervisor
    reports (its filtered s_k, a weighted mean of frames') lies within the range of the frames' own,
    computed here from the same depth files (3.80 to 4.01 m for ../shared/data/rgbd, +-2%); the
    edge detects on the frames; the drone is flown by the edge, with no fallback; when the recording
    has ended, the risk goes unknown after risk_stale_s, is logged once and read as high (q2)."""
    recording = tmp_path / "rgbd.db3"
    used = record(shared_data / "rgbd", recording, count=50, fps=5)
    spaciousness = Spaciousness(640, 480, INTRINSICS, stride=4)
    direct = []
    for n in sorted(set(used)):
        raw = cv2.imread(str(shared_data / "rgbd" / f"depth_{n}.pgm"), cv2.IMREAD_UNCHANGED)
        direct.append(spaciousness((raw * 0.001).astype(np.float32)))
    env = {"DYNQOS_ONBOARD__CAMERA": "realsense", "DYNQOS_ONBOARD__REALSENSE_FILE": str(recording)}
    with edge_loop(tmp_path) as (config, zcfg, procs):
        procs["detector"] = DynqosProcess(["edge", "detector"], config)
        observer = Observer(zcfg)
        statuses: BoundedQueue[Received] = BoundedQueue(10_000)
        observer.bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATUS), statuses)
        try:
            procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config, env=env)
            assert observer.wait_until(lambda s: s.mode == "offboard", 60), "the drone never offloaded"
            offboard_wall = time.time()
            seen: list[SupervisorStatus] = []
            deadline = time.monotonic() + 30  # the recording ends 10 s after the daemon started
            while time.monotonic() < deadline:
                item = statuses.get(1.0)
                if item is not None and isinstance(item.message, SupervisorStatus):
                    seen.append(item.message)
                    if item.message.depth_lost and item.message.state.value == "q2":
                        break
            observer.wait_until(lambda s: False, 2.0)  # flying blind on the priority flow
        finally:
            observer.bus.close()
        onboard = procs.pop("onboard").stop()
    seen += [i.message for i in statuses.drain() if isinstance(i.message, SupervisorStatus)]
    reported = [m.spaciousness_m for m in seen if m.spaciousness_m is not None]
    assert len(reported) >= 10, onboard[-2000:]
    known = [d for d in direct if d is not None]
    low, high = min(known) * 0.98, max(known) * 1.02
    assert all(low <= value <= high for value in reported), (min(reported), max(reported), known)
    assert "camera: RealSense" in onboard
    detections = [int(v) for v in re.findall(r" detections=(\d+)", onboard)]
    assert detections
    assert detections[-1] >= 10  # the edge's detector answered frames from the recording
    late = [m for t, m in log_times(onboard) if t >= offboard_wall and "fallback PID" in m]
    assert late == []
    # The recording ended: the risk went unknown after risk_stale_s, read as high: the priority flow.
    blind = [m for m in seen if m.depth_lost]
    assert blind, "depth never reported lost after the recording ended"
    assert all(m.risk == "NA" and m.spaciousness_m is None for m in blind)
    assert blind[-1].state.value == "q2"
    assert blind[-1].flow.value == "priority"
    assert "no depth for 2 s: risk unknown, read as high" in onboard
