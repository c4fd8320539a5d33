"""The simulated RGB-D camera: the world rendered from the drone's pose, as the onboard daemon's camera
source (common/camera.py). Whoever starts the daemon with `[onboard] camera = "sim"` hands it one."""

from __future__ import annotations

import numpy as np

from dynqos.common.camera import Pose, RawFrame
from dynqos.common.config import Config
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.render import Intrinsics, Renderer
from dynqos.sim.vehicle.world import World, default_world, load_world


class SimCamera:
    def __init__(self, world: World, width: int, height: int, seed: int = 0) -> None:
        intrinsics = Intrinsics(
            width=width,
            height=height,
            fx=525.0 * width / 640,
            fy=525.0 * height / 480,
            cx=(width - 1) / 2,
            cy=(height - 1) / 2,
        )
        # Rays are cast at 160 x 120 at most and the image resized; a smaller image (a fleet's scaled
        # camera) casts no more rays than it has pixels.
        render_size = (min(160, width), min(120, height))
        self.renderer = Renderer(world, intrinsics, render_size=render_size, seed=seed)

    @classmethod
    def for_drone(cls, config: Config) -> SimCamera:
        """The camera `[onboard]` describes, in its world (`world_file`, or the default arena)."""
        onboard = config.onboard
        world = load_world(onboard.world_file) if onboard.world_file else default_world()
        return cls(world, onboard.camera_width, onboard.camera_height, seed=config.supervisor.seed)

    def grab(self, pose: Pose | None) -> RawFrame | None:
        if pose is None:
            return None
        pos, quat = pose
        rgb, depth = self.renderer.render(np.array(pos), quat_to_rot(np.array(quat)))
        return RawFrame(rgb, depth.astype(np.float32), self.renderer.intrinsics.as_tuple())
