"""Config sections of the control loop: [supervisor], [control], [mpc], [planner] (and a drone's own
mission), [detector] and [onboard]."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Annotated, Literal

from dynqos.common.config.validate import In, _check_name, _check_replica_id, _host_port, _require, checked
from dynqos.common.keys import UAV_ID_PATTERN


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class SupervisorConfig:
    """The PFSM's parameters (paper eq. 1-3; docs/supervisor.md). Index 0/1/2 = camera/C&C/risk."""

    mode: Literal["deterministic", "stochastic"] = "deterministic"
    seed: int = 0
    mu: tuple[float, float, float] = (3.0, 5.0, 5.0)
    rho: tuple[float, float, float] = (61.0, 27.0, 3.0)
    w: tuple[float, float] = (0.35, 0.65)
    window: Annotated[tuple[int, int], In(1, 10_000, "window sizes must be in 1..10000", each=True)] = (
        10,
        50,
    )
    # t2 is the larger of the N2-sample mean and the mean of the last `cc_fast_window` RTTs (0: the
    # paper's t2 alone): quick to see a queue building, as slow as the paper to call it gone.
    cc_fast_window: int = 4
    th_lat: Annotated[float, In(0.0, 1.0, "must be in (0, 1)", lo_open=True, hi_open=True)] = 0.5
    risk_high_m: float = 3.0
    risk_medium_m: float = 5.0
    risk_a: Annotated[float, In(0.0, 1.0, "must be in [0, 1)", hi_open=True)] = 0.8
    risk_b: Annotated[float, In(0.0, 1.0, "must be in (0, 1]", lo_open=True)] = 0.2
    # Depth that stops (a camera gone, a recording ended, frames stalled) is held this long; after it
    # the risk is unknown and read as HR (docs/supervisor.md, "When depth stops").
    risk_stale_s: Annotated[float, In(0.1, 600, "must be in 0.1..600 s")] = 2.0
    dwell_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = 1.0
    persist_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = 0.1
    escalate_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = 3.0
    recover_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = 2.0
    probe_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = (
        1.0  # the camera tries the default flow this long before q1 (0: return at once)
    )
    recover_backoff: Annotated[float, In(1.0, 10.0, "must be in 1..10 (1 disables)")] = 2.0
    recover_max_s: float = 16.0
    rate_factor: float = 0.5
    min_rate_factor: float = 0.25
    # The camera's flow: "state" rides the state's (the paper: the whole application moves); "default"
    # keeps it on the default flow whatever the state's, so the state never waits behind the camera's
    # queue in the UE (docs/supervisor.md, "The camera's flow").
    camera_flow: Literal["state", "default"] = "state"
    rate_step_s: Annotated[float, In(0.0, 600, "must be in 0..600 s")] = 1.0
    watchdog_s: Annotated[float, In(0.001, 60, "must be in 0.001..60 s")] = 0.15
    # The modem's SINR as proactive evidence of high latency (docs/radio.md): off by default; on, a SINR
    # below radio_sinr_db raises P_lat before any sample shows the queue: P_lat = max(P_lat, P_radio),
    # P_radio = 1 - P(SINR; radio_mu, radio_sinr_db) (the paper's eq. 1 form, rising as the SINR falls)
    radio_aware: bool = False
    radio_sinr_db: Annotated[float, In(-23, 40, "must be in -23..40 dB")] = 6.0
    radio_mu: Annotated[float, In(0.01, 100, "must be in 0.01..100 per dB")] = 1.0
    # The 5G core's QoS monitoring reports (the priority flow's round trip, [qos.nef] qos_monitoring) as
    # evidence beside the windows: off by default; on, P_lat = max(P_lat, P(report; mu2, rho2)).
    network_aware: bool = False

    def __post_init__(self) -> None:
        _require(all(m > 0 for m in self.mu), "mu", "slopes must be > 0")
        _require(all(w >= 0 for w in self.w), "w", "weights must be >= 0")
        _require(
            math.isclose(sum(self.w), 1.0, abs_tol=1e-6), "w", f"weights must sum to 1, got {sum(self.w):g}"
        )
        _require(
            0 <= self.cc_fast_window <= self.window[1], "cc_fast_window", "must be in 0..window[1] (0: off)"
        )
        _require(0.0 < self.risk_high_m < self.risk_medium_m, "risk_medium_m", "must exceed risk_high_m > 0")
        _require(self.recover_max_s >= self.recover_s, "recover_max_s", "must be >= recover_s")
        _require(
            0.0 < self.min_rate_factor <= self.rate_factor <= 1.0,
            "rate_factor",
            "need 0 < min_rate_factor <= rate_factor <= 1",
        )


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class ControlConfig:
    t_mpc_s: Annotated[float, In(0.001, 1.0, "must be in 0.001..1 s")] = 0.05
    horizon: Annotated[int, In(5, 200, "must be in 5..200 steps")] = 20
    setpoint_hz: Annotated[
        float, In(2.0, 1000, "must be above 2 Hz (PX4 offboard) and <= 1000", lo_open=True)
    ] = 50.0  # the onboard daemon's tick: setpoints to the FC, the fallback PID's step


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class MpcConfig:
    """`dynqos edge mpc`; the step and horizon are [control] t_mpc_s and horizon."""

    q_pos: Annotated[float, In(0, 1e6, "must be in (0, 1e6]", lo_open=True)] = 10.0
    q_vel: Annotated[float, In(0, 1e6, "must be in (0, 1e6]", lo_open=True)] = 1.0
    r_acc: Annotated[float, In(0, 1e6, "must be in (0, 1e6]", lo_open=True)] = 0.1
    terminal_factor: Annotated[float, In(0, 1e6, "must be in (0, 1e6]", lo_open=True)] = 5.0
    v_max_mps: Annotated[
        tuple[float, float, float], In(0, 100, "each must be in (0, 100]", lo_open=True, each=True)
    ] = (3.0, 3.0, 1.5)
    a_max_mps2: Annotated[
        tuple[float, float, float], In(0, 100, "each must be in (0, 100]", lo_open=True, each=True)
    ] = (6.0, 6.0, 4.0)
    drag_per_s: Annotated[float, In(0, 10, "must be in 0..10 per second")] = 1.0
    eps: Annotated[float, In(1e-8, 1e-1, "must be in 1e-8..1e-1")] = 1e-4
    max_iter: Annotated[int, In(10, 100_000, "must be in 10..100000")] = 4000
    compensate_delay: bool = True
    command_steps: Annotated[int, In(1, 60, "must be in 1..60")] = 10
    max_compensation_s: Annotated[float, In(0, 2.5, "must be in 0..2.5 s")] = 1.0
    idle_timeout_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 10.0
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0
    # Replicas (docs/reliability.md): any number of `dynqos edge mpc` processes share the drones by
    # themselves. replica_id names this one (empty: <host>-<pid>); a standby takes a drone over when its
    # holder leaves a state unanswered this long (keep it well inside [supervisor] watchdog_s), and a
    # replica that was displaced waits holdoff_s before it takes a drone back by rank alone.
    replica_id: str = ""
    takeover_after_s: float = 0.05
    holdoff_s: float = 2.0
    # What a standby reads of a drone: "states", the drone's own states, kept newest-only in zenoh and
    # read twice a second (each beat period while the holder's beats are late), so a takeover answers
    # the newest at once; "copies", the holder's copy of its State twice a second (the router forwards
    # each state once, not twice; a takeover answers the drone's next state, up to two state periods
    # and a lease after the last command: only for a [supervisor] watchdog_s of 0.25 s or more).
    standby_reads: Literal["states", "copies"] = "states"
    # The edge site this replica belongs to ("" = one site). Replicas share drones and fence one another
    # within their site; each site answers every drone it serves, and a drone on two paths applies the
    # first Command for each state from whichever site (docs/multipath.md).
    site: str = ""
    # Static sharding (older deployments): shard_index of shard_count serves the drones with
    # crc32(id) % count == index. Replicas need none of it.
    shard_index: int = 0
    shard_count: Annotated[int, In(1, 1024, "must be in 1..1024")] = 1
    # Threads of the BLAS and OpenMP under numpy (OPENBLAS/OMP/MKL_NUM_THREADS, set before numpy loads;
    # an environment variable already set wins). Each QP is small and solved on one thread; left to
    # their default, every process starts one spinning thread per core, and replicas on one host fight
    # over them (docs/benchmarks.md, `edge_scale`).
    math_threads: Annotated[int, In(1, 256, "must be in 1..256")] = 1
    # The fresh states of all the drones this replica flies, solved together (edge/mpc/batch.py): one
    # matrix product for those whose bounds do not bind, OSQP for the rest. Off: one OSQP solve each.
    batch_solves: bool = True
    # How long the first fresh State of a turn waits for the others, so that they are taken and solved in
    # one turn (each turn of the loop has a cost of its own). A drone alone is answered at once. 0: off.
    batch_window_s: Annotated[float, In(0, 0.01, "must be in 0..0.01 s")] = 0.002

    def __post_init__(self) -> None:
        _check_replica(self.replica_id, self.takeover_after_s, self.holdoff_s, max_takeover_s=1.0)
        if self.site:
            _check_name(self.site, "site")
        _require(0 <= self.shard_index < self.shard_count, "shard_index", "must be in 0..shard_count-1")


def _check_replica(
    replica_id: str, takeover_after_s: float, holdoff_s: float, *, max_takeover_s: float
) -> None:
    _check_replica_id(replica_id)
    _require(
        0.005 <= takeover_after_s <= max_takeover_s,
        "takeover_after_s",
        f"must be in 0.005..{max_takeover_s:g} s",
    )
    _require(0 <= holdoff_s <= 600, "holdoff_s", "must be in 0..600 s")


def _check_mission(m: PlannerConfig | DroneMissionConfig) -> None:
    _require(0.2 <= m.altitude_m <= 100, "altitude_m", "must be in 0.2..100 m")
    _require(0.1 <= m.radius_m <= 100, "radius_m", "must be in 0.1..100 m")
    _require(1.0 <= m.period_s <= 3600, "period_s", "must be in 1..3600 s")
    _require(0.05 <= m.speed_mps <= 20, "speed_mps", "must be in 0.05..20 m/s")
    _require(
        m.mission != "waypoints" or bool(m.waypoints_file),
        "waypoints_file",
        "the waypoints mission needs a waypoints_file",
    )


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
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
@checked
class PlannerConfig:
    """`dynqos edge planner`: the mission every discovered drone flies (docs/edge.md)."""

    mission: Literal["hover", "circle", "figure8", "waypoints"] = "circle"
    center_m: tuple[float, float] = (0.0, 0.0)
    altitude_m: float = 1.5
    radius_m: float = 2.0
    period_s: float = 10.0
    yaw: Literal["tangent", "fixed", "center"] = "tangent"
    fixed_yaw_rad: float = 0.0
    lead_in_s: Annotated[float, In(0, 600, "must be in 0..600 s")] = 5.0
    waypoints_file: str = ""
    speed_mps: float = 1.0
    publish_hz: Annotated[float, In(0.5, 100, "must be in 0.5..100 Hz")] = 10.0
    samples: Annotated[int, In(2, 400, "must be in 2..400")] = 60
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0
    drones: dict[str, DroneMissionConfig] = field(default_factory=dict)  # drone id -> its own mission
    # Replicas (docs/reliability.md): as the MPC's; a standby takes a drone over when its holder has sent
    # no reference for takeover_after_s (several publish periods: the MPC has `samples` ahead meanwhile).
    replica_id: str = ""
    takeover_after_s: float = 0.5
    holdoff_s: float = 2.0
    # Where a mission from outside (a ROS 2 Path or goal) may take a drone: a box in local NED (metres;
    # down is positive, so the ceiling is arena_min_m's z and the floor arena_max_m's). A waypoint outside
    # it is refused, never flown.
    arena_min_m: tuple[float, float, float] = (-50.0, -50.0, -30.0)
    arena_max_m: tuple[float, float, float] = (50.0, 50.0, -0.3)

    def __post_init__(self) -> None:
        _check_mission(self)
        _check_replica(self.replica_id, self.takeover_after_s, self.holdoff_s, max_takeover_s=10.0)
        _require(
            all(lo < hi for lo, hi in zip(self.arena_min_m, self.arena_max_m, strict=True)),
            "arena_max_m",
            "must exceed arena_min_m on every axis",
        )
        for uav in self.drones:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"drones.{uav}", "is not a drone id")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class DetectorConfig:
    """`dynqos edge detector`: OpenCV HoughCircles on the RGB frames (docs/edge.md)."""

    channel: Literal["chroma", "gray"] = "chroma"
    dp: Annotated[float, In(0.5, 4, "must be in 0.5..4")] = 1.2
    min_dist_px: Annotated[float, In(1, 4000, "must be in 1..4000")] = 80.0
    canny_high: Annotated[float, In(1, 1000, "must be in 1..1000")] = 120.0
    accumulator: Annotated[float, In(1, 1000, "must be in 1..1000")] = 45.0
    min_radius_px: int = 12
    max_radius_px: int = 240
    blur_px: int = 5
    max_circles: Annotated[int, In(1, 64, "must be in 1..64")] = 16
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0
    # Several detectors share the drones (docs/edge.md); replica_id names this one (empty: <host>-<pid>).
    replica_id: str = ""

    def __post_init__(self) -> None:
        _require(
            1 <= self.min_radius_px < self.max_radius_px <= 4000,
            "max_radius_px",
            "need 1 <= min_radius_px < max_radius_px <= 4000",
        )
        _require(self.blur_px in (0, 3, 5, 7, 9), "blur_px", "must be 0, 3, 5, 7 or 9")
        _check_replica_id(self.replica_id)


MAX_PATHS = 4  # uplinks one drone may hold at once


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class OnboardPathConfig:
    """One of a drone's paths (docs/multipath.md): its own cell and operator, its own site's router."""

    name: str  # names the path in logs, statuses and reports (a, b, ...)
    connect_default: str  # host:port of this path's default flow
    connect_priority: str  # host:port of this path's priority flow
    # the edge site whose router this path dials ("" = the site named as the path): the drone's QoS
    # requests on this path are for that site's agent, which asks this path's operator
    site: str = ""

    def __post_init__(self) -> None:
        _check_name(self.name, "name")
        if self.site:
            _check_name(self.site, "site")
        for name in ("connect_default", "connect_priority"):
            _host_port(getattr(self, name), name)


MAX_TASKS = 16  # a drone's offloaded tasks, each with its own thread


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class OnboardConfig:
    """`dynqos onboard`: the drone's daemon (docs/onboard.md)."""

    mavlink_url: str = "udpin:127.0.0.1:14540"
    # The flight controller's MAVLink system and component ids (PX4: 1/1; instance N of a multi-vehicle
    # SITL is N+1), so that several vehicles can share a ground-station link.
    fc_system_id: Annotated[int, In(1, 255, "must be a MAVLink system id, 1..255")] = 1
    fc_component_id: Annotated[int, In(1, 255, "must be a MAVLink component id, 1..255")] = 1
    # MAVLink 2 signing (docs/onboard.md, "Signing"): a key file ("" = off), this link's id, and whether
    # the FC's unsigned messages are accepted anyway (PX4's HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE and
    # COLLISION always are).
    mavlink_flow_control: bool = False  # RTS/CTS on a serial mavlink_url (/dev/ttyACM0,921600)
    mavlink_signing_key: str = ""
    mavlink_link_id: Annotated[int, In(0, 255, "must be a MAVLink link id, 0..255")] = 1
    mavlink_accept_unsigned: bool = False
    # PX4's event catalogue (all_events.json.xz, made by every PX4 build): PX4's events, its arming
    # checks among them, reach the log as PX4's sentences ("" = by their id; docs/px4.md)
    px4_events: str = ""
    # command: the FC turns to the yaw of the edge's (or the fallback's) setpoint; free: the yaw is
    # ignored and the FC keeps its own heading (how every setpoint went out before 9231a8f).
    yaw: Literal["command", "free"] = "command"
    takeoff: bool = False
    takeoff_alt_m: Annotated[float, In(0.5, 100, "must be in 0.5..100 m")] = 1.5
    connect_default: str = ""  # host:port of the default flow ("" = zenoh edge_host:default_port)
    connect_priority: str = ""  # host:port of the priority flow ("" = zenoh edge_host:priority_port)
    # Two paths or more (docs/multipath.md): one zenoh session each, opened at once; states and statuses
    # go on every path, the camera on the best. Empty: one path, connect_default and connect_priority.
    paths: tuple[OnboardPathConfig, ...] = ()
    # When the Command applied comes from another site than the last, the acceleration setpoint moves by
    # at most this much at once, then towards the new site's plan by this much per setpoint period
    # (docs/multipath.md, "The setpoint step"); 0: no bound
    site_step_max_mps2: Annotated[float, In(0, 100, "must be in 0..100 m/s^2 (0: no bound)")] = 2.0
    qos: Literal["dynamic", "default", "priority"] = "dynamic"  # dynamic: the supervisor chooses
    camera: Literal["sim", "files", "device", "realsense", "none"] = "sim"
    camera_fps: Annotated[float, In(0, 120, "must be in 0..120")] = 15.0
    camera_width: int = 640
    camera_height: int = 480
    jpeg_quality: Annotated[int, In(1, 100, "must be in 1..100")] = 90
    # Pace camera bytes at this rate (0: each image goes out in one burst); set it a little below the
    # bearer's rate so images never queue in front of the state (docs/onboard.md, "Camera pacing").
    camera_pace_mbps: Annotated[float, In(0, 1e5, "must be in 0..100000 (0: no pacing)")] = 0.0
    camera_part_bytes: Annotated[int, In(512, 1 << 20, "must be in 512..1048576")] = (
        4096  # the size of one paced part
    )
    # The camera's frame rate from the edge's arrival reports (docs/camera.md): "delay" runs WebRTC's
    # delay-based estimator (aiortc's port) under the supervisor's rate factor, down to camera_rate_floor;
    # without a report for camera_feedback_timeout_s the rate halves, each timeout, to that floor
    camera_rate_control: Literal["none", "delay"] = "none"
    # the estimator's filter on the delay: "kalman" (aiortc's, WebRTC's 2016 one) or "trendline"
    # (libwebrtc's since, onboard/trendline.py)
    camera_delay_filter: Literal["kalman", "trendline"] = "kalman"
    # which controller reads the reports: "gcc" (WebRTC's, above) or "queue", a queue-delay target
    # (SCReAM v2's idea, onboard/queue_rate.py): slow to what arrived while an image meets a queue of
    # more than camera_queue_target_ms, climb while it meets less
    camera_rate_controller: Literal["gcc", "queue"] = "gcc"
    camera_queue_target_ms: Annotated[float, In(5, 2000, "must be in 5..2000 ms")] = 15.0
    camera_rate_floor: Annotated[float, In(0.01, 1.0, "must be in 0.01..1")] = 0.25
    camera_feedback_timeout_s: Annotated[float, In(0.1, 60, "must be in 0.1..60 s")] = 1.0
    files_dir: str = ""
    realsense_file: str = ""  # camera = "realsense": a recording to play back; "" = the first live device
    files_intrinsics: tuple[float, float, float, float] = (518.0, 519.0, 325.5, 253.5)
    device_index: int = 0
    world_file: str = ""
    on_exit: Literal["hold", "land"] = "hold"
    fallback: Literal["hold", "continue"] = "hold"  # continue: fly the last reference while it lasts
    fc_timeout_s: Annotated[float, In(1, 600, "must be in 1..600 s")] = 30.0
    heartbeat_timeout_s: Annotated[float, In(0.5, 60, "must be in 0.5..60 s")] = 3.0
    status_hz: Annotated[float, In(0.1, 50, "must be in 0.1..50 Hz")] = 5.0
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0
    # The modem's RSRP and SINR in each status (docs/radio.md): "mmcli" asks ModemManager on a real
    # drone, "cell" the emulated cell's GET /radio/<uav> at modem_url; a reading 3 intervals old is dropped
    modem: Literal["none", "mmcli", "cell"] = "none"
    modem_url: str = ""  # modem = "cell": e.g. http://127.0.0.1:40123/radio/uav1
    modem_command: str = "mmcli -m any --signal-get --output-json"
    modem_interval_s: Annotated[float, In(0.1, 60, "must be in 0.1..60 s")] = 1.0
    # The user's offloaded tasks the drone runs (docs/offload.md): each "MODULE:ATTR" or
    # "path/file.py:ATTR" naming a dynqos.offload.Onboard
    tasks: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _require(len(self.tasks) <= MAX_TASKS, "tasks", f"at most {MAX_TASKS} tasks")
        _require(
            all(isinstance(t, str) and ":" in t for t in self.tasks),
            "tasks",
            'name each task as "MODULE:ATTR" or "path/file.py:ATTR"',
        )
        _require(
            self.modem != "cell" or self.modem_url.startswith(("http://", "https://")),
            "modem_url",
            "the cell modem needs the cell's radio URL (http://HOST:PORT/radio/<uav>)",
        )
        _require(
            self.modem != "mmcli" or bool(self.modem_command.strip()), "modem_command", "must not be empty"
        )
        _require(
            bool(self.mavlink_url.strip()), "mavlink_url", "must not be empty (e.g. udpin:127.0.0.1:14540)"
        )
        for name in ("connect_default", "connect_priority"):
            if getattr(self, name):
                _host_port(getattr(self, name), name)
        _require(len(self.paths) <= MAX_PATHS, "paths", f"at most {MAX_PATHS} paths")
        _require(
            len({p.name for p in self.paths}) == len(self.paths), "paths", "each path needs its own name"
        )
        _require(
            not self.paths or not (self.connect_default or self.connect_priority),
            "paths",
            "give each path its endpoints, or connect_default/connect_priority for one path, not both",
        )
        _require(
            16 <= self.camera_width <= 4096 and 16 <= self.camera_height <= 4096,
            "camera_width",
            "image size must be 16..4096 pixels",
        )
        _require(
            self.camera != "files" or bool(self.files_dir), "files_dir", "the files camera needs files_dir"
        )


ROS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class Ros2Config:
    """`dynqos edge ros2`: the drones' topics for ROS 2 nodes, in rmw_zenoh's format (docs/ros2.md)."""

    domain_id: Annotated[int, In(0, 232, "must be in 0..232 (ROS 2 domain ids)")] = (
        0  # ROS_DOMAIN_ID of the ROS 2 nodes that should see the topics
    )
    prefix: str = "dynqos"  # topics are /<prefix>/<uav>/...
    frame_id: str = "map"  # the fixed ENU frame of poses and odometry
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0
    # The bridge translates what arrived every publish_period_s, on its own clock, not the moment each
    # state arrives (when the MPC is solving the same state: docs/ros2.md, "What it costs"); 0: at once.
    publish_period_s: Annotated[float, In(0, 1, "must be in 0..1 s")] = 0.05

    def __post_init__(self) -> None:
        _require(
            ROS_NAME.fullmatch(self.prefix) is not None,
            "prefix",
            "must be a ROS name: a letter, then letters, digits or _",
        )
        _require(
            ROS_NAME.fullmatch(self.frame_id) is not None,
            "frame_id",
            "must be a ROS frame name: a letter, then letters, digits or _",
        )
