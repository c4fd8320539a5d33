"""How large the scenario's camera images must be to offer the paper's rate from the views it flies.

Scaling the experiment down must shrink the frames, not the frame rate: a frame's serialisation time
through the scaled cell then stays what it is at full scale, and so do the latencies it causes. What a
frame weighs depends on what the camera sees: the floor fills more of the image the more the drone
tilts, and the pillars more of it near them. So the size is measured on the views of the mission the
scenario actually flies, with the attitude a drone flying it has (its acceleration sets the tilt) and
the heading it holds. Sized on the wrong views, a hovering drone offered 38 Mbit/s for 47: below its
fair share of the loaded cell (40.65), so the no-QoS scenario hardly queued at all.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from dynqos.common.config import Config
from dynqos.edge.planner.service import mission_from_config
from dynqos.sim.vehicle.dynamics import GRAVITY, rot_to_quat

Pose = tuple[tuple[float, float, float], tuple[float, float, float, float]]

VIEWS = 6  # poses per mission period
TAKEOFF_HEADING_RAD = 0.0  # the simulated vehicle starts facing north; `yaw = "free"` keeps it


def flight_views(config: Config, views: int = VIEWS) -> list[Pose]:
    """Camera poses along one period of the configured mission, each tilted by the acceleration the
    mission asks for there (thrust = a - g) and facing the heading the drone holds."""
    mission = mission_from_config(config.planner, config.drone.id)  # the drone's own, in a fleet
    period = mission.period_s
    start = mission.lead_in_s + 1e-3  # in the mission proper, not its lead-in
    step = 1e-3
    poses: list[Pose] = []
    for k in range(views):
        t = start + period * k / views
        pos, _, mission_yaw = mission.sample(t)
        before, after = mission.sample(t - step)[1], mission.sample(t + step)[1]
        accel = (np.array(after) - np.array(before)) / (2 * step)
        heading = TAKEOFF_HEADING_RAD if config.onboard.yaw == "free" else mission_yaw
        poses.append((pos, attitude(accel, heading)))
    return poses


def attitude(accel_ned: np.ndarray, yaw: float) -> tuple[float, float, float, float]:
    """The attitude (w, x, y, z) of a multirotor producing `accel_ned` with heading `yaw`: body z along
    the negative thrust, body x as close to the heading as that allows (as PX4's attitude setpoint)."""
    thrust = np.asarray(accel_ned, float) - np.array([0.0, 0.0, GRAVITY])
    z_body = -thrust / np.linalg.norm(thrust)
    y_body = np.cross(z_body, np.array([math.cos(yaw), math.sin(yaw), 0.0]))
    y_body /= np.linalg.norm(y_body)
    x_body = np.cross(y_body, z_body)
    w, x, y, z = rot_to_quat(np.column_stack([x_body, y_body, z_body]))
    return float(w), float(x), float(y), float(z)


def camera_size_for(
    target_bps: float, fps: float, views: Sequence[Pose], part_bytes: int = 0, world_file: str = ""
) -> tuple[int, int]:
    """A 4:3 image size whose RGB-D frames (JPEG + zstd16, in parts of `part_bytes` when paced) seen
    from `views` at `fps` offer about target_bps, message headers included. Small images compress
    worse per pixel, so the size found by area is measured and corrected twice."""
    width = 640
    for _ in range(3):
        bits = frame_bits(width, width * 3 // 4, views, part_bytes, world_file)
        linear = math.sqrt(target_bps / fps / bits)
        width = max(64, min(1280, round(width * linear / 4) * 4))
    return width, width * 3 // 4


def frame_bits(
    width: int, height: int, views: Sequence[Pose], part_bytes: int = 0, world_file: str = ""
) -> float:
    """Mean size in bits of one RGB-D frame on the wire, over `views` of the world the drone flies in."""
    from dynqos.onboard.camera import encode_depth, encode_rgb
    from dynqos.onboard.pacing import FRAME_HEADER_BYTES
    from dynqos.sim.vehicle.camera import SimCamera
    from dynqos.sim.vehicle.world import default_world, load_world

    world = load_world(world_file) if world_file else default_world()
    camera = SimCamera(world, width, height)  # the onboard camera's optics
    total = 0.0
    for pose in views:
        raw = camera.grab(pose)
        assert raw is not None
        assert raw.depth_m is not None
        for data in (encode_rgb(raw.rgb, 90), encode_depth(raw.depth_m)):
            messages = math.ceil(len(data) / part_bytes) if part_bytes else 1
            total += 8.0 * (len(data) + messages * FRAME_HEADER_BYTES)
    return total / len(views)
