"""Configuration: TOML files loaded into frozen, typed dataclasses.

Defaults are the paper's values where it gives them (mu, rho, w, N, risk thresholds, T_mpc) and
dynqos's own choices elsewhere (docs/supervisor.md says which and why). A file sets only what it
changes. Unknown keys, wrong types and out-of-range values are rejected with ConfigError naming the
file, the key path and the reason. Config is loaded once in `main()` and passed down; there are no
globals.
"""

from __future__ import annotations

import ipaddress
import math
import re
import sys
import types
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from dynqos.common.acl import reserved_name
from dynqos.common.errors import ConfigError, KeyExprError
from dynqos.common.keys import UAV_ID_PATTERN, check_uav_id

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

T = TypeVar("T")


def _require(condition: bool, key: str, reason: str) -> None:
    if not condition:
        raise ConfigError(key, reason)


@dataclass(frozen=True, slots=True, kw_only=True)
class DroneConfig:
    id: str = "uav1"

    def __post_init__(self) -> None:
        try:
            check_uav_id(self.id)
        except KeyExprError as exc:
            raise ConfigError("id", str(exc)) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohConfig:
    """How sessions reach the edge router. The two flows are two links to two router ports."""

    edge_host: str = "127.0.0.1"
    default_port: int = 7447
    priority_port: int = 7448
    router_listen_host: str = "127.0.0.1"
    max_links: int = 4
    shared_memory: bool = False
    priority_dscp: int = 0xB8
    bulk_sndbuf_bytes: int = 65536
    connect_timeout_s: float = 5.0
    # Production: mutual TLS on both flows, and on the router an access-control policy by certificate
    # common name (drone id; edge-mpc, edge-planner, edge-detector, edge-qos for the edge services).
    # See docs/security.md and `dynqos certs`.
    tls: bool = False
    tls_ca: str = ""  # the CA that signed every certificate (PEM)
    tls_cert: str = ""  # this process's certificate (PEM); CN = drone id, edge-<service> or "router"
    tls_key: str = ""  # its private key (PEM)
    acl_drones: tuple[str, ...] = ()  # router: the drone ids let in (each to its own keys only)
    # router with tls: "on" refuses to start without acl_drones (fail closed); "off" runs TLS with no
    # access control at all (every certificate from the CA may do anything), and says so loudly.
    acl: str = "on"

    def __post_init__(self) -> None:
        _require(bool(self.edge_host.strip()), "edge_host", "must not be empty")
        _require(bool(self.router_listen_host.strip()), "router_listen_host", "must not be empty")
        for name in ("default_port", "priority_port"):
            _require(1 <= getattr(self, name) <= 65535, name, "must be a TCP port in 1..65535")
        _require(self.default_port != self.priority_port, "priority_port", "must differ from default_port")
        _require(2 <= self.max_links <= 64, "max_links", "must be in 2..64 (two flows need two links)")
        _require(0 <= self.priority_dscp <= 0xFF, "priority_dscp", "must be a TOS byte in 0..255")
        _require(
            self.bulk_sndbuf_bytes == 0 or 4096 <= self.bulk_sndbuf_bytes <= 64 * 1024 * 1024,
            "bulk_sndbuf_bytes",
            "must be 0 (kernel default) or 4096..67108864",
        )
        _require(0.1 <= self.connect_timeout_s <= 600, "connect_timeout_s", "must be in 0.1..600 s")
        if self.tls:
            for name in ("tls_ca", "tls_cert", "tls_key"):
                _require(bool(getattr(self, name)), name, "must name a PEM file when tls = true")
        for uav in self.acl_drones:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, "acl_drones", f"{uav!r} is not a drone id")
            _require(not reserved_name(uav), "acl_drones", f"{uav!r} names an edge identity, not a drone")
        _require(not self.acl_drones or self.tls, "acl_drones", "access control needs tls = true")
        _require(self.acl in ("on", "off"), "acl", f'must be "on" or "off", got {self.acl!r}')
        _require(
            not (self.acl == "off" and self.acl_drones),
            "acl",
            'is "off" but acl_drones lists drones: say which you mean',
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class SupervisorConfig:
    """The PFSM's parameters (paper eq. 1-3; docs/supervisor.md). Index 0/1/2 = camera/C&C/risk."""

    mode: Literal["deterministic", "stochastic"] = "deterministic"
    seed: int = 0
    tick_hz: float = 20.0
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
        _require(0.1 <= self.tick_hz <= 1000, "tick_hz", "must be in 0.1..1000")
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
    setpoint_hz: float = 50.0

    def __post_init__(self) -> None:
        _require(0.001 <= self.t_mpc_s <= 1.0, "t_mpc_s", "must be in 0.001..1 s")
        _require(5 <= self.horizon <= 200, "horizon", "must be in 5..200 steps")
        _require(
            2.0 < self.setpoint_hz <= 1000, "setpoint_hz", "must be above 2 Hz (PX4 offboard) and <= 1000"
        )


def _host_port(text: str, key: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    _require(bool(sep and host), key, f"{text!r} is not host:port")
    _require(port.isdigit() and 1 <= int(port) <= 65535, key, f"{text!r}: port must be 1..65535")
    return host.strip("[]"), int(port)


@dataclass(frozen=True, slots=True, kw_only=True)
class BearerConfig:
    """One bearer (QoS flow) of the emulated cell: a TCP listener forwarding to an edge router port."""

    name: str
    target: str
    listen_port: int = 0  # 0: any free port, reported on the emulator's ready line
    weight: float = 1.0
    ue_buffer_bytes: int = 0  # 0: the cell's ue_buffer_bytes
    # The drone whose UE this bearer belongs to ("" = none). With [cell] qod = true a bearer of a drone
    # has its `weight` only while a QoD session for that drone's device and this bearer's target port
    # is AVAILABLE, and weight 1 otherwise (docs/qos.md).
    ue: str = ""

    def __post_init__(self) -> None:
        _require(not self.ue or UAV_ID_PATTERN.fullmatch(self.ue) is not None, "ue", "must be a drone id")
        _require(bool(self.name) and self.name.replace("-", "").replace("_", "").isalnum(), "name",
                 "must be letters, digits, - or _")  # fmt: skip
        _host_port(self.target, "target")
        _require(0 <= self.listen_port <= 65535, "listen_port", "must be 0..65535")
        _require(0 < self.weight <= 1000 and math.isfinite(self.weight), "weight", "must be in (0, 1000]")
        _require(0 <= self.ue_buffer_bytes <= 1 << 30, "ue_buffer_bytes", "must be 0..1 GiB")

    @property
    def target_host_port(self) -> tuple[str, int]:
        return _host_port(self.target, "target")


@dataclass(frozen=True, slots=True, kw_only=True)
class BackgroundConfig:
    """A virtual background user: it takes capacity at its offered rate; no bytes move."""

    name: str
    weight: float = 1.0
    offered_mbps: float = 0.0

    def __post_init__(self) -> None:
        _require(bool(self.name), "name", "must not be empty")
        _require(0 < self.weight <= 1000, "weight", "must be in (0, 1000]")
        _require(0 <= self.offered_mbps <= 1e5, "offered_mbps", "must be in 0..100000")


@dataclass(frozen=True, slots=True, kw_only=True)
class CellEventConfig:
    """A timeline event; which fields it needs depends on `kind` (see docs/cell.md)."""

    at_s: float
    kind: Literal["background", "capacity", "trace", "coverage_loss", "downlink_loss", "weight", "qod_end"]
    user: str = ""  # background: which background user
    bearer: str = ""  # weight: which bearer; coverage_loss with drop_connections: "" = all
    offered_mbps: float = -1.0  # background
    uplink_mbps: float = -1.0  # capacity
    file: str = ""  # trace: a Mahimahi uplink trace; "" ends trace-driven capacity
    mean_mbps: float = 0.0  # trace: rescale to this mean (0: as recorded)
    duration_s: float = 0.0  # coverage_loss, downlink_loss
    drop_connections: bool = False  # coverage_loss: also reset the TCP connections
    weight: float = 0.0  # weight
    uav: str = ""  # qod_end: whose QoD sessions the network ends ("" = every drone's)

    def __post_init__(self) -> None:
        _require(0 <= self.at_s <= 86400, "at_s", "must be in 0..86400 s")
        if self.kind == "background":
            _require(bool(self.user), "user", "a background event names its background user")
            _require(
                0 <= self.offered_mbps <= 1e5, "offered_mbps", "a background event needs offered_mbps >= 0"
            )
        elif self.kind == "capacity":
            _require(0 <= self.uplink_mbps <= 1e5, "uplink_mbps", "a capacity event needs uplink_mbps >= 0")
        elif self.kind in ("coverage_loss", "downlink_loss"):
            _require(0 < self.duration_s <= 3600, "duration_s", f"a {self.kind} event needs duration_s > 0")
        elif self.kind == "weight":
            _require(bool(self.bearer), "bearer", "a weight event names its bearer")
            _require(0 < self.weight <= 1000, "weight", "a weight event needs a weight in (0, 1000]")
        if self.kind == "trace":
            _require(self.mean_mbps >= 0, "mean_mbps", "must be >= 0")


@dataclass(frozen=True, slots=True, kw_only=True)
class CellConfig:
    """The emulated 5G cell (docs/cell.md). `scale` divides every rate."""

    uplink_mbps: float = 81.3
    downlink_mbps: float = 1400.0
    tti_ms: float = 1.0
    base_delay_up_ms: float = 10.0
    base_delay_down_ms: float = 10.0
    jitter_ms: float = 0.5
    scale: float = 1.0
    ue_buffer_bytes: int = 1_000_000
    listen_host: str = "127.0.0.1"
    default_listen_port: int = 17447
    priority_listen_port: int = 17448
    priority_weight: float = 4.0
    record_interval_s: float = 0.1
    control_port: int = -1  # -1: no control API; 0: any free port
    # The cell as an operator (docs/qos.md): with qod = true a drone's priority bearer gets its weight only
    # while a CAMARA Quality-on-Demand session grants it (the control port serves the QoD API); false is a
    # network with a static policy for the priority port (the `links` backend's assumption).
    qod: bool = False
    qod_max_sessions: int = -1  # sessions AVAILABLE at once (-1: no limit; 0: the operator grants none)
    qod_setup_s: float = 0.05  # REQUESTED -> AVAILABLE (or UNAVAILABLE when refused) after this long
    qod_max_duration_s: int = 86400  # a session's duration (with extensions) is capped here
    qod_profiles: tuple[str, ...] = ("QOS_E", "QOS_S", "QOS_M", "QOS_L")  # what the operator offers
    qod_auth: bool = False  # require OAuth2 client-credential tokens ([qos.camara] client_id/secret file)
    qod_token_ttl_s: float = 3600.0
    trace: str = ""
    trace_mean_mbps: float = 0.0
    seed: int = 0
    bearers: tuple[BearerConfig, ...] = ()  # empty: the drone's two flows (see bearer_list)
    background: tuple[BackgroundConfig, ...] = (BackgroundConfig(name="bg"),)
    events: tuple[CellEventConfig, ...] = ()

    def __post_init__(self) -> None:
        _require(0 <= self.uplink_mbps <= 1e5, "uplink_mbps", "must be in 0..100000")
        _require(0 < self.downlink_mbps <= 1e6, "downlink_mbps", "must be in (0, 1000000]")
        _require(0.1 <= self.tti_ms <= 100, "tti_ms", "must be in 0.1..100 ms")
        for name in ("base_delay_up_ms", "base_delay_down_ms", "jitter_ms"):
            _require(0 <= getattr(self, name) <= 10_000, name, "must be in 0..10000 ms")
        _require(0 < self.scale <= 1e4, "scale", "must be in (0, 10000]")
        _require(1500 <= self.ue_buffer_bytes <= 1 << 30, "ue_buffer_bytes", "must be 1500..1 GiB")
        _require(bool(self.listen_host), "listen_host", "must not be empty")
        for name in ("default_listen_port", "priority_listen_port"):
            _require(0 <= getattr(self, name) <= 65535, name, "must be 0..65535")
        _require(0 < self.priority_weight <= 1000, "priority_weight", "must be in (0, 1000]")
        _require(0.01 <= self.record_interval_s <= 60, "record_interval_s", "must be in 0.01..60 s")
        _require(-1 <= self.control_port <= 65535, "control_port", "must be -1 (off), 0 (any) or a port")
        _require(self.trace_mean_mbps >= 0, "trace_mean_mbps", "must be >= 0")
        _require(self.qod_max_sessions >= -1, "qod_max_sessions", "must be -1 (no limit) or >= 0")
        _require(0 <= self.qod_setup_s <= 60, "qod_setup_s", "must be in 0..60 s")
        _require(1 <= self.qod_max_duration_s <= 10**7, "qod_max_duration_s", "must be in 1..10000000 s")
        _require(1 <= self.qod_token_ttl_s <= 86400, "qod_token_ttl_s", "must be in 1..86400 s")
        names = [b.name for b in self.bearers]
        _require(len(set(names)) == len(names), "bearers", "bearer names must be unique")
        users = [b.name for b in self.background]
        _require(len(set(users)) == len(users), "background", "background user names must be unique")
        for i, event in enumerate(self.events):
            if event.kind == "background" and event.user not in users:
                raise ConfigError(
                    f"events[{i}].user", f"unknown background user {event.user!r} (known: {users})"
                )

    def bearer_list(self, zenoh: ZenohConfig, uav: str) -> tuple[BearerConfig, ...]:
        """The configured bearers, or the drone's default and priority flows to the edge router."""
        if self.bearers:
            return self.bearers
        host = zenoh.edge_host
        return (
            BearerConfig(name=f"{uav}-default", target=f"{host}:{zenoh.default_port}",
                         listen_port=self.default_listen_port, weight=1.0, ue=uav),
            BearerConfig(name=f"{uav}-priority", target=f"{host}:{zenoh.priority_port}",
                         listen_port=self.priority_listen_port, weight=self.priority_weight, ue=uav),
        )  # fmt: skip


@dataclass(frozen=True, slots=True, kw_only=True)
class VehicleSimConfig:
    """`dynqos sim vehicle`: the simulated quadrotor's MAVLink links (PX4 SITL's ports) and world."""

    host: str = "127.0.0.1"
    offboard_bind_port: int = 14580
    offboard_remote_port: int = 14540
    gcs_bind_port: int = 18570
    gcs_remote_port: int = 14550
    speed: float = 1.0
    wind_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = 0.0
    gust_tau_s: float = 2.0  # the gusts' correlation time
    seed: int = 0
    takeoff_alt_m: float = 2.5
    offboard_loss_s: float = 1.0
    lockstep: bool = False  # advance 20 ms per answer from the offboard peer instead of real time
    world_file: str = ""  # TOML/JSON world for contact checks; "" = the default arena
    start_m: tuple[float, float] = (0.0, 0.0)  # where it stands before take-off (north, east), local NED

    def __post_init__(self) -> None:
        for name in ("offboard_bind_port", "offboard_remote_port", "gcs_bind_port", "gcs_remote_port"):
            _require(0 <= getattr(self, name) <= 65535, name, "must be 0..65535 (0: any free port)")
        _require(0.01 <= self.speed <= 100, "speed", "must be in 0.01..100 (x real time)")
        _require(all(abs(w) <= 30 for w in self.wind_mps), "wind_mps", "components must be within 30 m/s")
        _require(0 <= self.gust_std_mps <= 10, "gust_std_mps", "must be in 0..10 m/s")
        _require(0.05 <= self.gust_tau_s <= 600, "gust_tau_s", "must be in 0.05..600 s")
        _require(0.5 <= self.takeoff_alt_m <= 100, "takeoff_alt_m", "must be in 0.5..100 m")
        _require(0.1 <= self.offboard_loss_s <= 60, "offboard_loss_s", "must be in 0.1..60 s (COM_OF_LOSS_T)")
        _require(all(abs(c) <= 1e4 for c in self.start_m), "start_m", "must be within 10 km of the origin")


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
    # Scale-out: replica shard_index of shard_count serves the drones with crc32(id) % count == index.
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
        _require(1 <= self.shard_count <= 1024, "shard_count", "must be in 1..1024")
        _require(0 <= self.shard_index < self.shard_count, "shard_index", "must be in 0..shard_count-1")
        _require(0.5 <= self.idle_timeout_s <= 3600, "idle_timeout_s", "must be in 0.5..3600 s")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")


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

    def __post_init__(self) -> None:
        _check_mission(self)
        _require(0 <= self.lead_in_s <= 600, "lead_in_s", "must be in 0..600 s")
        _require(0.5 <= self.publish_hz <= 100, "publish_hz", "must be in 0.5..100 Hz")
        _require(2 <= self.samples <= 400, "samples", "must be in 2..400")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")
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

    def __post_init__(self) -> None:
        _require(0.5 <= self.dp <= 4, "dp", "must be in 0.5..4")
        _require(1 <= self.min_dist_px <= 4000, "min_dist_px", "must be in 1..4000")
        _require(1 <= self.canny_high <= 1000, "canny_high", "must be in 1..1000")
        _require(1 <= self.accumulator <= 1000, "accumulator", "must be in 1..1000")
        _require(1 <= self.min_radius_px < self.max_radius_px <= 4000, "max_radius_px",
                 "need 1 <= min_radius_px < max_radius_px <= 4000")  # fmt: skip
        _require(self.blur_px in (0, 3, 5, 7, 9), "blur_px", "must be 0, 3, 5, 7 or 9")
        _require(1 <= self.max_circles <= 64, "max_circles", "must be in 1..64")
        _require(0.5 <= self.health_interval_s <= 3600, "health_interval_s", "must be in 0.5..3600 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class OnboardConfig:
    """`dynqos onboard`: the drone's daemon (docs/onboard.md)."""

    mavlink_url: str = "udpin:127.0.0.1:14540"
    # The flight controller's MAVLink system and component ids (PX4: 1/1; instance N of a multi-vehicle
    # SITL is N+1), so that several vehicles can share a ground-station link.
    fc_system_id: int = 1
    fc_component_id: int = 1
    # command: the FC turns to the yaw of the edge's (or the fallback's) setpoint; free: the yaw is
    # ignored and the FC keeps its own heading (how every setpoint went out before wave 2).
    yaw: Literal["command", "free"] = "command"
    takeoff: bool = False
    takeoff_alt_m: float = 1.5
    connect_default: str = ""  # host:port of the default flow ("" = zenoh edge_host:default_port)
    connect_priority: str = ""  # host:port of the priority flow ("" = zenoh edge_host:priority_port)
    qos: Literal["dynamic", "default", "priority"] = "dynamic"  # dynamic: the supervisor chooses
    camera: Literal["sim", "files", "device", "none"] = "sim"
    camera_fps: float = 15.0
    camera_width: int = 640
    camera_height: int = 480
    jpeg_quality: int = 90
    # Pace camera bytes at this rate (0: each image goes out in one burst); set it a little below the
    # bearer's rate so images never queue in front of the state (docs/onboard.md, "Camera pacing").
    camera_pace_mbps: float = 0.0
    camera_part_bytes: int = 4096  # the size of one paced part
    files_dir: str = ""
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


_PHONE_NUMBER = re.compile(r"\+[1-9][0-9]{4,14}")


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceIpv4Config:
    """CAMARA DeviceIpv4Addr: the public address, with the private address or the public port."""

    publicAddress: str = ""
    privateAddress: str = ""
    publicPort: int = 0

    def __post_init__(self) -> None:
        for name in ("publicAddress", "privateAddress"):
            value = getattr(self, name)
            if value:
                try:
                    ipaddress.IPv4Address(value)
                except ValueError:
                    raise ConfigError(name, f"{value!r} is not an IPv4 address") from None
        _require(0 <= self.publicPort <= 65535, "publicPort", "must be a port in 1..65535 (0: not given)")
        if self.privateAddress or self.publicPort:
            _require(
                bool(self.publicAddress), "publicAddress", "is required with privateAddress or publicPort"
            )
        if self.publicAddress:
            _require(bool(self.privateAddress or self.publicPort), "publicAddress",
                     "needs privateAddress or publicPort as well (CAMARA DeviceIpv4Addr)")  # fmt: skip


@dataclass(frozen=True, slots=True, kw_only=True)
class DeviceConfig:
    """A drone's identity on the operator's network: a CAMARA `device` object (at least one identifier)."""

    phoneNumber: str = ""
    networkAccessIdentifier: str = ""
    ipv4Address: DeviceIpv4Config = field(default_factory=DeviceIpv4Config)
    ipv6Address: str = ""

    def __post_init__(self) -> None:
        if self.phoneNumber:
            _require(_PHONE_NUMBER.fullmatch(self.phoneNumber) is not None, "phoneNumber",
                     f"{self.phoneNumber!r} is not E.164 with a leading + (e.g. +46700000001)")  # fmt: skip
        if self.ipv6Address:
            try:
                ipaddress.IPv6Address(self.ipv6Address)
            except ValueError:
                raise ConfigError("ipv6Address", f"{self.ipv6Address!r} is not an IPv6 address") from None
        ids = "phoneNumber, ipv4Address, ipv6Address, networkAccessIdentifier"
        _require(bool(self.as_api()), "device", f"needs at least one of {ids}")

    def as_api(self) -> dict[str, Any]:
        """The CAMARA `device` object: only the identifiers given."""
        out: dict[str, Any] = {}
        if self.phoneNumber:
            out["phoneNumber"] = self.phoneNumber
        if self.networkAccessIdentifier:
            out["networkAccessIdentifier"] = self.networkAccessIdentifier
        ipv4 = {k: v for k, v in asdict(self.ipv4Address).items() if v}
        if ipv4:
            out["ipv4Address"] = ipv4
        if self.ipv6Address:
            out["ipv6Address"] = self.ipv6Address
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class CamaraConfig:
    """[qos.camara]: a CAMARA Quality-on-Demand API (v1.1.0) the agent asks for QoS sessions."""

    api_root: str = ""  # e.g. https://api.operator.example/quality-on-demand/v1
    token_url: str = ""  # OAuth2 token endpoint for client credentials ("" = no token)
    client_id: str = ""
    client_secret_file: str = ""  # a file holding the client secret (never the secret itself)
    qos_profile: str = "QOS_E"
    duration_s: int = 600  # requested per session; extended while priority is still wanted
    extend_before_s: float = 30.0  # extend when the session has less than this left
    # A session the operator capped (an extend did not move its end) is replaced this long before it ends
    renew_before_s: float = 2.0
    application_server: str = ""  # the edge address the network sees ("" = [zenoh] edge_host)
    sink: str = ""  # notifications URL given to the operator ("" = polling only)
    sink_listen: str = ""  # host:port the agent serves that URL on ("" = no listener)
    poll_interval_s: float = 0.2  # how often a REQUESTED session is read until it settles
    timeout_s: float = 2.0  # every HTTP call ends within this
    retry_after_denied_s: float = 10.0  # a denied drone asks again after this (doubling, up to 8x)
    devices: dict[str, DeviceConfig] = field(default_factory=dict)  # drone id -> its device

    def __post_init__(self) -> None:
        for name in ("api_root", "token_url", "sink"):
            url = getattr(self, name)
            _require(not url or url.startswith(("http://", "https://")), name, "must be an http(s) URL")
        _require(len(self.qos_profile) >= 3 and re.fullmatch(r"[A-Za-z0-9_.-]{3,256}", self.qos_profile)
                 is not None, "qos_profile", "must be 3..256 of A-Z a-z 0-9 _ . -")  # fmt: skip
        _require(1 <= self.duration_s <= 10**7, "duration_s", "must be in 1..10000000 s")
        _require(0 <= self.extend_before_s < self.duration_s, "extend_before_s", "must be in 0..duration_s")
        _require(0 <= self.renew_before_s < self.duration_s, "renew_before_s", "must be in 0..duration_s")
        _require(0.01 <= self.poll_interval_s <= 60, "poll_interval_s", "must be in 0.01..60 s")
        _require(0.05 <= self.timeout_s <= 60, "timeout_s", "must be in 0.05..60 s")
        _require(0.1 <= self.retry_after_denied_s <= 3600, "retry_after_denied_s", "must be in 0.1..3600 s")
        if self.sink_listen:
            _host_port(self.sink_listen, "sink_listen")
        if self.token_url:
            _require(bool(self.client_id), "client_id", "is required with token_url")
            _require(bool(self.client_secret_file), "client_secret_file", "is required with token_url")
        for uav in self.devices:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"devices.{uav}", "is not a drone id")


@dataclass(frozen=True, slots=True, kw_only=True)
class ArbiterConfig:
    """[qos.arbiter]: the budget and the timers of `policy = "arbiter"` (edge/arbiter.py, docs/fleet.md)."""

    max_grants: int = -1  # at most this many drones hold priority at once (-1: no limit by count)
    max_share: float = 1.0  # ...and together offer at most this share of uplink_mbps (1: no limit)
    uplink_mbps: float = 0.0  # the cell's uplink the share is of (what the operator contracts)
    min_hold_s: float = 3.0  # a grant is revoked for higher latency alone only after this long
    rotate_after_s: float = 30.0  # drones of equal need take turns this often

    def __post_init__(self) -> None:
        _require(-1 <= self.max_grants <= 10_000, "max_grants", "must be -1 (no limit) or 0..10000")
        _require(0 < self.max_share <= 1, "max_share", "must be in (0, 1]")
        _require(0 <= self.uplink_mbps <= 1e6, "uplink_mbps", "must be in 0..1000000 Mbit/s")
        _require(self.max_share == 1 or self.uplink_mbps > 0, "uplink_mbps",
                 "is required (> 0) when max_share is below 1")  # fmt: skip
        _require(0 <= self.min_hold_s <= 3600, "min_hold_s", "must be in 0..3600 s")
        _require(0.1 <= self.rotate_after_s <= 3600, "rotate_after_s", "must be in 0.1..3600 s")
        _require(self.rotate_after_s >= self.min_hold_s, "rotate_after_s", "must be at least min_hold_s")


@dataclass(frozen=True, slots=True, kw_only=True)
class QosConfig:
    """[qos]: how the network is asked for the priority flow (`dynqos edge qos`, docs/qos.md)."""

    backend: Literal["links", "camara"] = "links"
    hold_down_s: float = 5.0  # release a session only after the drone left priority this long
    request_interval_s: float = 1.0  # the drone repeats its request this often
    drone_timeout_s: float = 5.0  # the agent treats a drone it has not heard from this long as gone
    agent_timeout_s: float = 3.0  # the drone reports "no agent" after this long without a grant
    grant_interval_s: float = 1.0  # the agent repeats each drone's grant this often
    health_interval_s: float = 5.0
    # Who gets priority: every drone that asks, or (arbiter) the neediest within [qos.arbiter]'s budget.
    policy: Literal["grant-all", "arbiter"] = "grant-all"
    camara: CamaraConfig = field(default_factory=CamaraConfig)
    arbiter: ArbiterConfig = field(default_factory=ArbiterConfig)

    def __post_init__(self) -> None:
        for name in ("hold_down_s", "request_interval_s", "drone_timeout_s", "agent_timeout_s",
                     "grant_interval_s", "health_interval_s"):  # fmt: skip
            _require(0 <= getattr(self, name) <= 3600, name, "must be in 0..3600 s")
        _require(self.request_interval_s >= 0.05, "request_interval_s", "must be >= 0.05 s")
        _require(self.grant_interval_s >= 0.05, "grant_interval_s", "must be >= 0.05 s")
        _require(self.drone_timeout_s > self.request_interval_s, "drone_timeout_s",
                 "must exceed request_interval_s")  # fmt: skip
        _require(self.agent_timeout_s > self.grant_interval_s, "agent_timeout_s",
                 "must exceed grant_interval_s")  # fmt: skip
        if self.backend == "camara":
            _require(bool(self.camara.api_root), "camara.api_root", 'is required with backend = "camara"')
        # With links the network prioritises whoever uses the priority port: a revoked grant could not
        # be taken back, so the arbiter's budget would be a wish.
        _require(self.policy != "arbiter" or self.backend == "camara", "policy",
                 'the arbiter needs backend = "camara" (a network that enforces its grants)')  # fmt: skip


@dataclass(frozen=True, slots=True, kw_only=True)
class MetricsConfig:
    """Prometheus metrics and a health endpoint of a long-running process (docs/observability.md)."""

    port: int = 0  # /metrics and /healthz on this TCP port; 0 = off (the default, the drone's too)
    host: str = "127.0.0.1"  # where they listen; 0.0.0.0 in a pod, so that Prometheus can scrape it
    stale_after_s: float = 30.0  # /healthz answers 503 when the last health line is older than this

    def __post_init__(self) -> None:
        _require(0 <= self.port <= 65535, "port", "must be 0 (off) or a TCP port in 1..65535")
        _require(bool(self.host.strip()), "host", "must not be empty")
        _require(1.0 <= self.stale_after_s <= 3600, "stale_after_s", "must be in 1..3600 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class Config:
    drone: DroneConfig = field(default_factory=DroneConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    cell: CellConfig = field(default_factory=CellConfig)
    vehicle: VehicleSimConfig = field(default_factory=VehicleSimConfig)
    mpc: MpcConfig = field(default_factory=MpcConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    onboard: OnboardConfig = field(default_factory=OnboardConfig)
    qos: QosConfig = field(default_factory=QosConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)

    def __post_init__(self) -> None:
        bearers = {b.name for b in self.cell.bearer_list(self.zenoh, self.drone.id)}
        for i, event in enumerate(self.cell.events):
            if event.kind == "weight" and event.bearer not in bearers:
                raise ConfigError(
                    f"cell.events[{i}].bearer", f"unknown bearer {event.bearer!r} (known: {sorted(bearers)})"
                )
            if event.kind == "coverage_loss" and event.bearer and event.bearer not in bearers:
                raise ConfigError(
                    f"cell.events[{i}].bearer", f"unknown bearer {event.bearer!r} (known: {sorted(bearers)})"
                )


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, key: str) -> Any:  # noqa: C901 (one case per TOML type a field may have)
    origin = get_origin(tp)
    if is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return build(tp, value, key)
    if origin is Literal:
        options = get_args(tp)
        if value not in options:
            raise ConfigError(key, f"{value!r} is not one of {', '.join(map(repr, options))}")
        return value
    if origin is dict:
        value_type = get_args(tp)[1]
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return {str(k): _convert(value_type, v, f"{key}.{k}") for k, v in value.items()}
    if origin in (Union, types.UnionType):
        raise ConfigError(key, "unsupported type")  # pragma: no cover - no optional settings yet
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(key, f"expected an array, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(key, f"expected an array of {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"expected a string, got {value!r}")
        return value
    raise ConfigError(key, f"unsupported setting type {_type_name(tp)}")  # pragma: no cover


def build(cls: type[T], table: dict[str, Any], prefix: str = "") -> T:
    """A dataclass from a TOML table; every error names the full key path."""
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    for name in table:
        if name not in known:
            path = f"{prefix}.{name}" if prefix else name
            raise ConfigError(path, f"unknown key (known: {', '.join(sorted(known))})")
    kwargs = {}
    for name, value in table.items():
        path = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(hints[name], value, path)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise exc.under(prefix) if prefix else exc from None


def _parse_override(text: str) -> tuple[list[str], Any]:
    if "=" not in text:
        raise ConfigError("", f"--set {text!r}: expected KEY=VALUE, e.g. supervisor.th_lat=0.6")
    key, raw = text.split("=", 1)
    key = key.strip()
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()  # a bare word is a string
    parts = key.split(".")
    if not all(parts):
        raise ConfigError(key, "--set: empty key part")
    return parts, value


def _merge(table: dict[str, Any], parts: list[str], value: Any) -> None:
    node = table
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(".".join(parts), f"{part} is not a table")
        node = child
    node[parts[-1]] = value


ENV_PREFIX = "DYNQOS_"
ENV_NESTING = "__"


def environment_overrides(environ: Mapping[str, str]) -> list[tuple[str, str]]:
    """Settings from the environment, the Kubernetes way: `DYNQOS_<SECTION>__<KEY>=VALUE` (nested as
    pydantic-settings nests them: `DYNQOS_QOS__CAMARA__API_ROOT`), case-insensitive, as
    (variable, `section.key=value`) pairs in a stable order. Variables without `__` (such as a test's
    `DYNQOS_SOAK_S`) are not settings."""
    found = []
    for name in sorted(environ):
        rest = name[len(ENV_PREFIX) :] if name.upper().startswith(ENV_PREFIX) else ""
        if ENV_NESTING in rest:
            path = ".".join(part.lower() for part in rest.split(ENV_NESTING))
            found.append((name, f"{path}={environ[name]}"))
    return found


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    *,
    environment: list[tuple[str, str]] | tuple[tuple[str, str], ...] = (),
) -> Config:
    """Load a TOML file (or the defaults when path is None), then apply `environment` (from
    `environment_overrides`) and then the `--set KEY=VALUE` overrides: the later wins."""
    table: dict[str, Any] = {}
    source = "<defaults>"
    if path is not None:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError("", "config file not found", source=source) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError("", f"cannot read config file ({exc})", source=source) from None
        try:
            table = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"not valid TOML ({exc})", source=source) from None
    by_key: dict[str, str] = {}  # setting -> the variable or option that set it last
    for variable, text in environment:
        parts, value = _parse_override(text)
        _merge(table, parts, value)
        by_key[".".join(parts)] = f"environment variable {variable}"
    for text in overrides:
        parts, value = _parse_override(text)
        _merge(table, parts, value)
        by_key[".".join(parts)] = "--set"
    try:
        return build(Config, table)
    except ConfigError as exc:
        named = [who for key, who in by_key.items() if _related(exc.key, key)]
        raise exc.with_source(named[-1] if named else source) from None


def _related(a: str, b: str) -> bool:
    """One key path is the other or lies inside it (`qos` and `qos.camara.api_root`)."""
    return a == b or a.startswith(b + ".") or b.startswith(a + ".")


def to_dict(config: Config) -> dict[str, Any]:
    return asdict(config)


def to_toml(config: Config) -> str:
    """The effective config as TOML (what `dynqos config show` prints)."""
    lines: list[str] = []
    for section, values in to_dict(config).items():
        lines.append(f"[{section}]")
        tables = {
            k: v for k, v in values.items() if isinstance(v, (list, tuple)) and v and isinstance(v[0], dict)
        }
        for key, value in values.items():
            if key not in tables:
                lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
        for key, items in tables.items():
            for item in items:
                lines.append(f"[[{section}.{key}]]")
                lines.extend(f"{k} = {_toml_value(v)}" for k, v in item.items())
                lines.append("")
    return "\n".join(lines)


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else _toml_value(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):  # a nested table, inline
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")  # pragma: no cover
