"""A RealSense recording made in a test, with librealsense itself, from real RGB-D frames on disk.

A `software_device` with a depth sensor (z16, the frames' millimetres, depth units 0.001) and a colour
sensor (rgb8), both with the frames' intrinsics, recorded by `rs.recorder` (librealsense 2.59 writes
ROS 2 .db3 bags). Frames are injected at the camera's pace: the recorder stamps on arrival and drops
what comes faster. Nothing large is committed: the recording lives in the test's tmp folder.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

INTRINSICS = (518.0, 519.0, 325.5, 253.5)  # the frames' (../shared/data/README.md)


def _profile(sensor: Any, kind: Any, fmt: Any, bpp: int, uid: int, size: tuple[int, int], fps: int) -> Any:
    import pyrealsense2 as rs  # loaded only where the test's librealsense fixture let it run

    fx, fy, cx, cy = INTRINSICS
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height = size
    intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy = fx, fy, cx, cy
    intrinsics.model = rs.distortion.none
    intrinsics.coeffs = [0.0] * 5
    stream = rs.video_stream()
    stream.type, stream.index, stream.uid = kind, 0, uid
    stream.width, stream.height = size
    stream.fps, stream.bpp, stream.fmt, stream.intrinsics = fps, bpp, fmt, intrinsics
    return sensor.add_video_stream(stream)


def record(
    frames_dir: Path,
    out: Path,
    *,
    count: int,
    fps: int = 15,
    lag_ms: dict[int, float] | None = None,
    stamps_ms: list[float] | None = None,
) -> list[int]:
    """Write `count` frames (color_N.png + depth_N.pgm of `frames_dir`, in a loop) to `out` (.db3);
    return the frame numbers used, in order. `lag_ms`: frame N's device stamp that much earlier than it
    was handed over, as if it had waited in the driver; `stamps_ms` gets each frame's device stamp."""
    import pyrealsense2 as rs

    numbers = sorted(int(p.stem.split("_")[1]) for p in frames_dir.glob("depth_*.pgm"))
    images = {
        n: (cv2.imread(str(frames_dir / f"depth_{n}.pgm"), cv2.IMREAD_UNCHANGED),
            cv2.cvtColor(cv2.imread(str(frames_dir / f"color_{n}.png")), cv2.COLOR_BGR2RGB))
        for n in numbers
    }  # fmt: skip
    h, w = images[numbers[0]][0].shape
    device = rs.software_device()
    depth_sensor, color_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    depth = _profile(depth_sensor, rs.stream.depth, rs.format.z16, 2, 0, (w, h), fps)
    color = _profile(color_sensor, rs.stream.color, rs.format.rgb8, 3, 1, (w, h), fps)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(out), device)
    sink = rs.frame_queue(2 * count)
    depth_sensor.open(depth)
    color_sensor.open(color)
    depth_sensor.start(sink)
    color_sensor.start(sink)
    used = []
    next_at = time.monotonic()
    for k in range(count):
        n = numbers[k % len(numbers)]
        stamp_ms = time.time() * 1000.0 - (lag_ms or {}).get(n, 0.0)
        for sensor, profile, image, bpp in ((depth_sensor, depth, images[n][0], 2),
                                            (color_sensor, color, images[n][1], 3)):  # fmt: skip
            frame = rs.software_video_frame()
            frame.pixels = np.ascontiguousarray(image)
            frame.stride, frame.bpp = w * bpp, bpp
            frame.timestamp, frame.domain = stamp_ms, rs.timestamp_domain.hardware_clock
            frame.frame_number, frame.profile = k + 1, profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
        used.append(n)
        if stamps_ms is not None:
            stamps_ms.append(stamp_ms)
        next_at += 1.0 / fps
        time.sleep(max(0.0, next_at - time.monotonic()))  # the camera's pace: the recorder stamps on arrival
    for sensor in (depth_sensor, color_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # closes the file
    return used
