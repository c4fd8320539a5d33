"""An Intel RealSense depth camera through librealsense's own Python wrapper (pyrealsense2), live from a
device or played back from a recording (`[onboard] realsense_file`).

What a real depth camera gives that the `device` source cannot: depth, aligned to the colour image
(`rs.align`), in metres by the device's own depth scale, with the device's own intrinsics (the colour
stream's, since depth is aligned to it), not configured ones, and the device's frame timestamps, put
on the daemon's clock (onboard/frame_time.py) as the frame's capture time. A live device is asked for
`camera_width` x `camera_height` at `camera_fps` for both streams, and refused in one line when it
cannot give them. A recording plays at its recorded pace and ends; after its end `grab` gives
nothing (the camera stream then sends nothing, as with a camera that stopped).

pyrealsense2 comes with the `realsense` extra and needs `libusb-1.0` from the system (docs/onboard.md).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from dynqos.common.camera import Pose, RawFrame
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.errors import ConfigError
from dynqos.onboard.frame_time import DeviceTime

log = logging.getLogger(__name__)

WAIT_MS = 100  # the longest grab waits for a frame: the camera thread stays responsive to a stop


def _pyrealsense2() -> Any:
    try:
        import pyrealsense2 as rs  # optional: the realsense extra
    except ImportError as exc:
        raise ConfigError(
            "onboard.camera",
            f'"realsense" needs pyrealsense2 ({exc}): pip install "dynqos[realsense]", and libusb-1.0 '
            "from the system (apt install libusb-1.0-0)",
        ) from None
    return rs


class RealSenseCamera:
    def __init__(self, file: str, width: int, height: int, fps: float, clock: Clock | None = None) -> None:
        rs = _pyrealsense2()
        self.file = file
        self.clock = clock or MonotonicClock()
        self.device_time = DeviceTime()
        config = rs.config()
        if file:
            if not Path(file).is_file():
                raise ConfigError("onboard.realsense_file", f"no such recording: {file}")
            config.enable_device_from_file(file, repeat_playback=False)
        else:
            if len(rs.context().query_devices()) == 0:
                raise ConfigError("onboard.camera", "no RealSense device is connected")
            rate = round(fps)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, rate)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, rate)
            if not config.can_resolve(rs.pipeline_wrapper(rs.pipeline())):
                raise ConfigError(
                    "onboard.camera_width",
                    f"the RealSense device cannot stream depth and colour at {width}x{height}, {rate} fps",
                )
        self.pipeline = rs.pipeline()
        try:
            profile = self.pipeline.start(config)
        except RuntimeError as exc:  # a recording librealsense cannot read, a device that went away
            raise ConfigError("onboard.camera", f"cannot start the RealSense pipeline: {exc}") from None
        device = profile.get_device()
        if file:
            device.as_playback().set_real_time(True)  # at the recorded pace, as the camera gave it
        self.depth_scale = float(device.first_depth_sensor().get_depth_scale())
        self.align = rs.align(rs.stream.color)
        self.frames = 0
        name = rs.camera_info.name
        model = device.get_info(name) if device.supports(name) else "(unnamed)"
        where = f"recording {file}" if file else "live"
        log.info("camera: RealSense %s (%s), depth scale %.6f m", model, where, self.depth_scale)

    def grab(self, pose: Pose | None) -> RawFrame | None:
        ok, frames = self.pipeline.try_wait_for_frames(WAIT_MS)
        if not ok:
            return None
        arrival_ns, wall_ns = self.clock.now_ns(), time.time_ns()
        aligned = self.align.process(frames)
        depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
        if not depth or not color:
            return None
        i = color.get_profile().as_video_stream_profile().get_intrinsics()
        depth_m = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_scale)
        rgb = np.array(np.asanyarray(color.get_data()), dtype=np.uint8)  # a copy: the buffer is reused
        self.frames += 1
        domain = color.get_frame_timestamp_domain().name  # e.g. "hardware_clock", "global_time"
        captured = self.device_time.captured_ns(color.get_timestamp(), domain, arrival_ns, wall_ns)
        intrinsics = (float(i.fx), float(i.fy), float(i.ppx), float(i.ppy))
        return RawFrame(rgb, depth_m, intrinsics, captured)

    def close(self) -> None:
        self.pipeline.stop()
