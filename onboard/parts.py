"""What the drone's daemon is built from, as [onboard] configures it: the link to the flight controller,
the camera, and the take-off's commands on that link. Split from onboard/daemon.py so that the
preflight (onboard/check.py) and the benchmarks build the same parts without the daemon."""

from __future__ import annotations

from collections.abc import Callable

from dynqos.common import mavsign
from dynqos.common.camera import CameraSource
from dynqos.common.clock import Clock
from dynqos.common.config import Config
from dynqos.common.errors import ConfigError
from dynqos.onboard.camera import DeviceCamera, FilesCamera
from dynqos.onboard.fclink import PX4_MAIN_OFFBOARD, FcLink
from dynqos.onboard.px4_events import EventCatalogue
from dynqos.onboard.takeoff import Do


def takeoff_commands(link: FcLink, altitude_m: float) -> dict[Do, Callable[[int], int | None]]:
    """What each command step of the take-off (onboard/takeoff.py) sends on the FC link, given its
    confirmation count; the FC's answer (MAV_RESULT, or None) is what `TakeoffSequencer.answered` takes."""
    return {
        Do.TAKEOFF_ALTITUDE: lambda _c: link.set_param("MIS_TAKEOFF_ALT", altitude_m),
        Do.ARM: link.arm,
        Do.TAKE_OFF: lambda c: link.takeoff(confirmation=c),
        Do.OFFBOARD: lambda c: link.set_mode(PX4_MAIN_OFFBOARD, confirmation=c),
    }


def fc_link(config: Config, clock: Clock | None = None) -> FcLink:
    """The link to the flight controller as [onboard] configures it (not started)."""
    cfg = config.onboard
    return FcLink(
        cfg.mavlink_url,
        clock=clock,
        heartbeat_timeout_s=cfg.heartbeat_timeout_s,
        fc_system_id=cfg.fc_system_id,
        fc_component_id=cfg.fc_component_id,
        fly_yaw=cfg.yaw == "command",
        flow_control=cfg.mavlink_flow_control,
        signing_key=mavsign.load_key(cfg.mavlink_signing_key) if cfg.mavlink_signing_key else None,
        link_id=cfg.mavlink_link_id,
        accept_unsigned=cfg.mavlink_accept_unsigned,
        events=EventCatalogue.load(cfg.px4_events) if cfg.px4_events else None,
    )


def camera_source(config: Config, sim_camera: CameraSource | None) -> CameraSource | None:
    """The configured camera (None: none); `sim_camera`, the simulator's, for camera = "sim"."""
    cfg = config.onboard
    if cfg.camera == "none" or cfg.camera_fps == 0:
        return None
    if cfg.camera == "sim":
        if sim_camera is None:
            raise ConfigError(
                "onboard.camera", '"sim" renders from the simulator, which this start did not hand over'
            )
        return sim_camera
    if cfg.camera == "files":
        return FilesCamera(cfg.files_dir, cfg.files_intrinsics)
    if cfg.camera == "realsense":
        from dynqos.onboard.realsense import RealSenseCamera

        return RealSenseCamera(cfg.realsense_file, cfg.camera_width, cfg.camera_height, cfg.camera_fps)
    return DeviceCamera(cfg.device_index, cfg.camera_width, cfg.camera_height, cfg.files_intrinsics)
