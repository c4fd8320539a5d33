"""Config sections of the control loop: [supervisor], [control], [mpc], [planner] (and a drone's own
mission), [detector] and [onboard]."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Literal

from dynqos.common.config.validate import _check_replica_id, _host_port, _require
from dynqos.common.keys import UAV_ID_PATTERN


@dataclass(frozen=True, slots=True, kw_only=True)
class SupervisorConfig:
    """The PFSM's parameters (paper eq. 1-3; docs/supervisor.md). Index 0/1/2 = camera/C&C/risk."""

    mode: Literal["deterministic", "stochastic"] = "deterministic"
    seed: int = 0
    mu: tuple[float, float, float] = (3.0, 5.0, 5.0)
    rho: tuple[float, float, float] = (61.0, 27.0, 3.0)
    w: tuple[float, float] = (0.35, 0.65)
    window: tuple[int, int] = (10, 50)
    # t2 is the larger of the N2-sample mean and the mean of the last `cc_fast_window` RTTs (0: the
    # paper's t2 alone): quick to see a queue building, as slow as the paper to call it gone.
    cc_fast_window: int = 4
    th_lat: float = 0.5
    risk_high_m: float = 3.0
    risk_medium_m: float = 5.0
    risk_a: float = 0.8
    risk_b: float = 0.2
    # Depth that stops (a camera gone, a recording ended, frames stalled) is held this long; after it
    # the risk is unknown and read as HR (docs/supervisor.md, "When depth stops").
    risk_stale_s: float = 2.0
    dwell_s: float = 1.0
    persist_s: float = 0.1
    escalate_s: float = 3.0
    recover_s: float = 2.0
    probe_s: float = 1.0  # the camera tries the default flow this long before q1 (0: return at once)
    recover_backoff: float = 2.0
    recover_max_s: float = 16.0
    rate_factor: float = 0.5
    min_rate_factor: float = 0.25
    rate_step_s: float = 1.0
    watchdog_s: float = 0.15

    def __post_init__(self) -> None:
        _require(all(m > 0 for m in self.mu), "mu", "slopes must be > 0")
        _require(all(w >= 0 for w in self.w), "w", "weights must be >= 0")
        _require(
            math.isclose(sum(self.w), 1.0, abs_tol=1e-6), "w", f"weights must sum to 1, got {sum(self.w):g}"
        )
        _require(all(1 <= n <= 10_000 for n in self.window), "window", "window sizes must be in 1..10000")
        _require(
            0 <= self.cc_fast_window <= self.window[1], "cc_fast_window", "must be in 0..window[1] (0: off)"
        )
        _require(0.0 < self.th_lat < 1.0, "th_lat", "must be in (0, 1)")
        _require(0.0 < self.risk_high_m < self.risk_medium_m, "risk_medium_m", "must exceed risk_high_m > 0")
        _require(0.0 <= self.risk_a < 1.0, "risk_a", "must be in [0, 1)")
        _require(0.0 < self.risk_b <= 1.0, "risk_b", "must be in (0, 1]")
        _require(0.1 <= self.risk_stale_s <= 600, "risk_stale_s", "must be in 0.1..600 s")
        for name in ("dwell_s", "persist_s", "escalate_s", "recover_s", "probe_s", "rate_step_s"):
            _require(0.0 <= getattr(self, name) <= 600, name, "must be in 0..600 s")
        _require(1.0 <= self.recover_backoff <= 10.0, "recover_backoff", "must be in 1..10 (1 disables)")
        _require(self.recover_max_s >= self.recover_s, "recover_max_s", "must be >= recover_s")
        _require(
            0.0 < self.min_rate_factor <= self.rate_factor <= 1.0,
            "rate_factor",
            "need 0 < min_rate_factor <= rate_factor <= 1",
        )
        _require(0.001 <= self.watchdog_s <= 60, "watchdog_s", "must be in 0.001..60 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class ControlConfig:
    t_mpc_s: float = 0.05
    horizon: int = 20
    setpoint_hz: float = 50.0  # the onboard daemon's tick: setpoints to the FC, the fallback PID's step

    def __post_init__(self) -> None:
        _require(0.001 <= self.t_mpc_s <= 1.0, "t_mpc_s", "must be in 0.001..1 s")
        _require(5 <= self.horizon <= 200, "horizon", "must be in 5..200 steps")
        _require(
            2.0 < self.setpoint_hz <= 1000, "setpoint_hz", "must be above 2 Hz (PX4 offboard) and <= 1000"
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class MpcConfig:
    """`dynqos edge mpc`; the step and horizon are [control] t_mpc_s and horizon."""

    q_pos: float = 10.0
    q_vel: float = 1.0
    r_acc: float = 0.1
    terminal_factor: float = 5.0
    v_max_mps: tuple[float, float, float] = (3.0, 3.0, 1.5)
    a_max_mps2: tuple[float, float, float] = (6.0, 6.0, 4.0)
    drag_per_s: float = 0.25
    eps: float = 1e-4
    max_iter: int = 4000
    compensate_delay: bool = True
    command_steps: int = 10
    max_compensation_s: float = 1.0
    idle_timeout_s: float = 10.0
    health_interval_s: float = 5.0
    # Replicas (docs/reliability.md): any number of `dynqos edge mpc` processes share the drones by
    # themselves. replica_id names this one (empty: <host>-<pid>); a standby takes a drone over when its
    # holder leaves a state unanswered this long (keep it well inside [supervisor] watchdog_s), and a
    # replica that was displaced waits holdoff_s before it takes a drone back by rank alone.
    replica_id: str = ""
    takeover_after_s: float = 0.05
    holdoff_s: float = 2.0
    # Static sharding (older deployments): shard_index of shard_count serves the drones with
    # crc32(id) % count == index. Replicas need none of it.
    shard_index: int = 0
    shard_count: int = 1

    def __post_init__(self) -> None:
        for name in ("q_pos", "q_vel", "r_acc", "terminal_factor"):
            _require(0 < getattr(self, name) <= 1e6, name, "must be in (0, 1e6]")
        _require(all(0 < v <= 100 for v in self.v_max_mps), "v_max_mps", "each must be in (0, 100]")
        _require(all(0 < a <= 100 for a in self.a_max_mps2), "a_max_mps2", "each must be in (0, 100]")
        _require(0 <= self.drag_per_s <= 10, "drag_per_s", "must be in 0..10 per second")
        _require(1e-8 <= self.eps <= 1e-1, "eps", "must be in 1e-8..1e-1")
        _require(10 <= self.max_iter <= 100_000, "max_iter", "must be in 10..100000")
        _require(1 <= self.command_steps <= 60, "command_steps", "must be in 1..60")
        _require(0 <= self.max_compensation_s <= 2.5, "max_compensation_s", "must be in 0..2.5 s")
        _check_replica(self.replica_id, self.takeover_after_s, self.holdoff_s, max_takeover_s=1.0)
        _require(1 <= self.shard_count <= 1024, "shard_count", "must be in 1..1024")
        _require(0 <= self.shard_index < self.shard_count, "shard_index", "must be in 0..shard_count-1")
        _require(0.5 <= self.idle_timeout_s <= 3600, "idle_timeout_s", "must be in 0.5..3600 s")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")


def _check_replica(
    replica_id: str, takeover_after_s: float, holdoff_s: float, *, max_takeover_s: float
) -> None:
    _check_replica_id(replica_id)
    _require(0.005 <= takeover_after_s <= max_takeover_s, "takeover_after_s",
             f"must be in 0.005..{max_takeover_s:g} s")  # fmt: skip
    _require(0 <= holdoff_s <= 600, "holdoff_s", "must be in 0..600 s")


def _check_mission(m: PlannerConfig | DroneMissionConfig) -> None:
    _require(0.2 <= m.altitude_m <= 100, "altitude_m", "must be in 0.2..100 m")
    _require(0.1 <= m.radius_m <= 100, "radius_m", "must be in 0.1..100 m")
    _require(1.0 <= m.period_s <= 3600, "period_s", "must be in 1..3600 s")
    _require(0.05 <= m.speed_mps <= 20, "speed_mps", "must be in 0.05..20 m/s")
    _require(m.mission != "waypoints" or bool(m.waypoints_file), "waypoints_file",
             "the waypoints mission needs a waypoints_file")  # fmt: skip


@dataclass(frozen=True, slots=True, kw_only=True)
class DroneMissionConfig:
    """[planner.drones.<uav>]: the mission one drone of a fleet flies instead of the planner's. It is a
    whole mission: keys it leaves out take these defaults, not the planner's."""

    mission: Literal["hover", "circle", "figure8", "waypoints"] = "circle"
    center_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 1.5
    radius_m: float = 2.0
    period_s: float = 10.0
    yaw: Literal["tangent", "fixed", "center"] = "tangent"
    fixed_yaw_rad: float = 0.0
    waypoints_file: str = ""
    speed_mps: float = 1.0

    def __post_init__(self) -> None:
        _check_mission(self)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlannerConfig:
    """`dynqos edge planner`: the mission every discovered drone flies (docs/edge.md)."""

    mission: Literal["hover", "circle", "figure8", "waypoints"] = "circle"
    center_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 1.5
    radius_m: float = 2.0
    period_s: float = 10.0
    yaw: Literal["tangent", "fixed", "center"] = "tangent"
    fixed_yaw_rad: float = 0.0
    lead_in_s: float = 5.0
    waypoints_file: str = ""
    speed_mps: float = 1.0
    publish_hz: float = 10.0
    samples: int = 60
    health_interval_s: float = 5.0
    drones: dict[str, DroneMissionConfig] = field(default_factory=dict)  # drone id -> its own mission
    # Replicas (docs/reliability.md): as the MPC's; a standby takes a drone over when its holder has sent
    # no reference for takeover_after_s (several publish periods: the MPC has `samples` ahead meanwhile).
    replica_id: str = ""
    takeover_after_s: float = 0.5
    holdoff_s: float = 2.0

    def __post_init__(self) -> None:
        _check_mission(self)
        _require(0 <= self.lead_in_s <= 600, "lead_in_s", "must be in 0..600 s")
        _require(0.5 <= self.publish_hz <= 100, "publish_hz", "must be in 0.5..100 Hz")
        _require(2 <= self.samples <= 400, "samples", "must be in 2..400")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")
        _check_replica(self.replica_id, self.takeover_after_s, self.holdoff_s, max_takeover_s=10.0)
        for uav in self.drones:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"drones.{uav}", "is not a drone id")


@dataclass(frozen=True, slots=True, kw_only=True)
class DetectorConfig:
    """`dynqos edge detector`: OpenCV HoughCircles on the RGB frames (docs/edge.md)."""

    channel: Literal["chroma", "gray"] = "chroma"
    dp: float = 1.2
    min_dist_px: float = 80.0
    canny_high: float = 120.0
    accumulator: float = 45.0
    min_radius_px: int = 12
    max_radius_px: int = 240
    blur_px: int = 5
    max_circles: int = 16
    health_interval_s: float = 5.0
    # Several detectors share the drones (docs/edge.md); replica_id names this one (empty: <host>-<pid>).
    replica_id: str = ""

    def __post_init__(self) -> None:
        _require(0.5 <= self.dp <= 4, "dp", "must be in 0.5..4")
        _require(1 <= self.min_dist_px <= 4000, "min_dist_px", "must be in 1..4000")
        _require(1 <= self.canny_high <= 1000, "canny_high", "must be in 1..1000")
        _require(1 <= self.accumulator <= 1000, "accumulator", "must be in 1..1000")
        _require(1 <= self.min_radius_px < self.max_radius_px <= 4000, "max_radius_px",
                 "need 1 <= min_radius_px < max_radius_px <= 4000")  # fmt: skip
        _require(self.blur_px in (0, 3, 5, 7, 9), "blur_px", "must be 0, 3, 5, 7 or 9")
        _require(1 <= self.max_circles <= 64, "max_circles", "must be in 1..64")
        _check_replica_id(self.replica_id)
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class OnboardConfig:
    """`dynqos onboard`: the drone's daemon (docs/onboard.md)."""

    mavlink_url: str = "udpin:127.0.0.1:14540"
    # The flight controller's MAVLink system and component ids (PX4: 1/1; instance N of a multi-vehicle
    # SITL is N+1), so that several vehicles can share a ground-station link.
    fc_system_id: int = 1
    fc_component_id: int = 1
    # MAVLink 2 signing (docs/onboard.md, "Signing"): a key file ("" = off), this link's id, and whether
    # the FC's unsigned messages are accepted anyway (PX4's HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and
    # COLLISION always are).
    mavlink_flow_control: bool = False  # RTS/CTS on a serial mavlink_url (/dev/ttyACM0,921600)
    mavlink_signing_key: str = ""
    mavlink_link_id: int = 1
    mavlink_accept_unsigned: bool = False
    # command: the FC turns to the yaw of the edge's (or the fallback's) setpoint; free: the yaw is
    # ignored and the FC keeps its own heading (how every setpoint went out before 9231a8f).
    yaw: Literal["command", "free"] = "command"
    takeoff: bool = False
    takeoff_alt_m: float = 1.5
    connect_default: str = ""  # host:port of the default flow ("" = zenoh edge_host:default_port)
    connect_priority: str = ""  # host:port of the priority flow ("" = zenoh edge_host:priority_port)
    qos: Literal["dynamic", "default", "priority"] = "dynamic"  # dynamic: the supervisor chooses
    camera: Literal["sim", "files", "device", "realsense", "none"] = "sim"
    camera_fps: float = 15.0
    camera_width: int = 640
    camera_height: int = 480
    jpeg_quality: int = 90
    # Pace camera bytes at this rate (0: each image goes out in one burst); set it a little below the
    # bearer's rate so images never queue in front of the state (docs/onboard.md, "Camera pacing").
    camera_pace_mbps: float = 0.0
    camera_part_bytes: int = 4096  # the size of one paced part
    files_dir: str = ""
    realsense_file: str = ""  # camera = "realsense": a recording to play back; "" = the first live device
    files_intrinsics: tuple[float, float, float, float] = (518.0, 519.0, 325.5, 253.5)
    device_index: int = 0
    world_file: str = ""
    on_exit: Literal["hold", "land"] = "hold"
    fallback: Literal["hold", "continue"] = "hold"  # continue: fly the last reference while it lasts
    fc_timeout_s: float = 30.0
    heartbeat_timeout_s: float = 3.0
    status_hz: float = 5.0
    health_interval_s: float = 5.0

    def __post_init__(self) -> None:
        _require(
            bool(self.mavlink_url.strip()), "mavlink_url", "must not be empty (e.g. udpin:127.0.0.1:14540)"
        )
        _require(0.5 <= self.takeoff_alt_m <= 100, "takeoff_alt_m", "must be in 0.5..100 m")
        _require(1 <= self.fc_system_id <= 255, "fc_system_id", "must be a MAVLink system id, 1..255")
        _require(
            1 <= self.fc_component_id <= 255, "fc_component_id", "must be a MAVLink component id, 1..255"
        )
        _require(0 <= self.mavlink_link_id <= 255, "mavlink_link_id", "must be a MAVLink link id, 0..255")
        for name in ("connect_default", "connect_priority"):
            if getattr(self, name):
                _host_port(getattr(self, name), name)
        _require(0 <= self.camera_fps <= 120, "camera_fps", "must be in 0..120")
        _require(16 <= self.camera_width <= 4096 and 16 <= self.camera_height <= 4096, "camera_width",
                 "image size must be 16..4096 pixels")  # fmt: skip
        _require(1 <= self.jpeg_quality <= 100, "jpeg_quality", "must be in 1..100")
        _require(
            0 <= self.camera_pace_mbps <= 1e5 and math.isfinite(self.camera_pace_mbps),
            "camera_pace_mbps",
            "must be in 0..100000 (0: no pacing)",
        )
        _require(512 <= self.camera_part_bytes <= 1 << 20, "camera_part_bytes", "must be in 512..1048576")
        _require(
            self.camera != "files" or bool(self.files_dir), "files_dir", "the files camera needs files_dir"
        )
        _require(1 <= self.fc_timeout_s <= 600, "fc_timeout_s", "must be in 1..600 s")
        _require(0.5 <= self.heartbeat_timeout_s <= 60, "heartbeat_timeout_s", "must be in 0.5..60 s")
        _require(0.1 <= self.status_hz <= 50, "status_hz", "must be in 0.1..50 Hz")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")


ROS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


@dataclass(frozen=True, slots=True, kw_only=True)
class Ros2Config:
    """`dynqos edge ros2`: the drones' topics for ROS 2 nodes, in rmw_zenoh's format (docs/ros2.md)."""

    domain_id: int = 0  # ROS_DOMAIN_ID of the ROS 2 nodes that should see the topics
    prefix: str = "dynqos"  # topics are /<prefix>/<uav>/...
    frame_id: str = "map"  # the fixed ENU frame of poses and odometry
    health_interval_s: float = 5.0

    def __post_init__(self) -> None:
        _require(0 <= self.domain_id <= 232, "domain_id", "must be in 0..232 (ROS 2 domain ids)")
        _require(ROS_NAME.fullmatch(self.prefix) is not None, "prefix",
                 "must be a ROS name: a letter, then letters, digits or _")  # fmt: skip
        _require(ROS_NAME.fullmatch(self.frame_id) is not None, "frame_id",
                 "must be a ROS frame name: a letter, then letters, digits or _")  # fmt: skip
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")
