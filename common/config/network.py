"""Config sections of the network and the stand-ins: [drone], [zenoh], [cell] (bearers, background users,
timeline events), [vehicle] and [metrics]."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Annotated, Literal

from dynqos.common.acl import reserved_name
from dynqos.common.config.radio import PredictionConfig, RadioConfig
from dynqos.common.config.validate import In, _host_port, _require, checked
from dynqos.common.errors import ConfigError, KeyExprError
from dynqos.common.keys import TASK_NAME_PATTERN, TASK_NAME_RULE, UAV_ID_PATTERN, check_uav_id


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class DroneConfig:
    id: str = "uav1"

    def __post_init__(self) -> None:
        try:
            check_uav_id(self.id)
        except KeyExprError as exc:
            raise ConfigError("id", str(exc)) from None


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class ZenohConfig:
    """How sessions reach the edge router. The two flows are two links to two router ports."""

    edge_host: str = "127.0.0.1"
    default_port: Annotated[int, In(1, 65535, "must be a TCP port in 1..65535")] = 7447
    priority_port: Annotated[int, In(1, 65535, "must be a TCP port in 1..65535")] = 7448
    router_listen_host: str = "127.0.0.1"
    max_links: Annotated[int, In(2, 64, "must be in 2..64 (two flows need two links)")] = 4
    shared_memory: bool = False
    priority_dscp: Annotated[int, In(0, 0xFF, "must be a TOS byte in 0..255")] = 0xB8
    bulk_sndbuf_bytes: int = 65536
    connect_timeout_s: Annotated[float, In(0.1, 600, "must be in 0.1..600 s")] = 5.0
    # Production: mutual TLS on both flows, and on the router an access-control policy by certificate
    # common name (drone id; edge-mpc, edge-planner, edge-fleet-planner, edge-detector, edge-qos,
    # edge-ros2 for the edge services).
    # See docs/security.md and `dynqos certs`.
    tls: bool = False
    tls_ca: str = ""  # the CA that signed every certificate (PEM)
    tls_cert: str = ""  # this process's certificate (PEM); CN = drone id, edge-<service> or "router"
    tls_key: str = ""  # its private key (PEM)
    acl_drones: tuple[str, ...] = ()  # router: the drone ids let in (each to its own keys only)
    # router with tls: "on" refuses to start without acl_drones (fail closed); "off" runs TLS with no
    # access control at all (every certificate from the CA may do anything), and says so loudly.
    acl: str = "on"
    # router with access control: ROS 2 nodes let in by certificate CN, to read what `dynqos edge ros2`
    # publishes and nothing else; the domain and prefix are the bridge's [ros2] domain_id and prefix
    acl_ros2_clients: tuple[str, ...] = ()
    acl_ros2_domain_id: Annotated[int, In(0, 232, "must be in 0..232 (ROS 2 domain ids)")] = 0
    acl_ros2_prefix: str = "dynqos"
    # router with access control: the user's offloaded tasks let in (docs/offload.md), each service by
    # its identity edge-task-<name> and to its own task's keys only
    acl_tasks: tuple[str, ...] = ()
    # router: the routers of other edge sites to link to (zenoh endpoints, `tcp/<host>:<port>`), so that
    # replicas at both sites see each other's tokens and share the drones (docs/deploy.md)
    router_links: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        _require(bool(self.edge_host.strip()), "edge_host", "must not be empty")
        _require(bool(self.router_listen_host.strip()), "router_listen_host", "must not be empty")
        _require(self.default_port != self.priority_port, "priority_port", "must differ from default_port")
        _require(
            self.bulk_sndbuf_bytes == 0 or 4096 <= self.bulk_sndbuf_bytes <= 64 * 1024 * 1024,
            "bulk_sndbuf_bytes",
            "must be 0 (kernel default) or 4096..67108864",
        )
        if self.tls:
            for name in ("tls_ca", "tls_cert", "tls_key"):
                _require(bool(getattr(self, name)), name, "must name a PEM file when tls = true")
        for uav in self.acl_drones:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, "acl_drones", f"{uav!r} is not a drone id")
            _require(not reserved_name(uav), "acl_drones", f"{uav!r} names an edge identity, not a drone")
        _require(not self.acl_drones or self.tls, "acl_drones", "access control needs tls = true")
        for name in self.acl_ros2_clients:
            ok = UAV_ID_PATTERN.fullmatch(name) is not None and not reserved_name(name)
            _require(ok, "acl_ros2_clients", f"{name!r}: 1 to 32 of A-Z a-z 0-9 _ -, not an edge identity")
            _require(name not in self.acl_drones, "acl_ros2_clients", f"{name!r} is a drone's identity")
        _require(
            not self.acl_ros2_clients or bool(self.acl_drones),
            "acl_ros2_clients",
            "needs the router's access control (acl_drones)",
        )
        _require(
            re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", self.acl_ros2_prefix) is not None,
            "acl_ros2_prefix",
            "must be a ROS name: a letter, then letters, digits, _",
        )
        for task in self.acl_tasks:
            _require(
                TASK_NAME_PATTERN.fullmatch(task) is not None, "acl_tasks", f"{task!r}: {TASK_NAME_RULE}"
            )
        _require(
            not self.acl_tasks or bool(self.acl_drones), "acl_tasks", "needs the router's access control"
        )
        _require(self.acl in ("on", "off"), "acl", f'must be "on" or "off", got {self.acl!r}')
        for link in self.router_links:
            scheme = "tls" if self.tls else "tcp"
            _require(
                re.fullmatch(rf"{scheme}/\S+:\d{{1,5}}", link) is not None,
                "router_links",
                f"{link!r} is not a zenoh endpoint: write {scheme}/<host>:<port>",
            )
        _require(
            not (self.router_links and self.acl_drones),
            "router_links",
            "cannot link routers under access control yet: the policy has no rule for another "
            "router (link the sites over a private network with acl_drones empty, or run zenohd "
            "with a policy of your own)",
        )
        _require(
            not (self.acl == "off" and self.acl_drones),
            "acl",
            'is "off" but acl_drones lists drones: say which you mean',
        )


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class BearerConfig:
    """One bearer (QoS flow) of the emulated cell: a TCP listener forwarding to an edge router port."""

    name: str
    target: str
    listen_port: Annotated[int, In(0, 65535, "must be 0..65535")] = (
        0  # 0: any free port, reported on the emulator's ready line
    )
    weight: Annotated[float, In(0, 1000, "must be in (0, 1000]", lo_open=True)] = 1.0
    ue_buffer_bytes: Annotated[int, In(0, 1 << 30, "must be 0..1 GiB")] = 0  # 0: the cell's ue_buffer_bytes
    # The drone whose UE this bearer belongs to ("" = none). With [cell] qod = true a bearer of a drone
    # has its `weight` only while a QoD session for that drone's device and this bearer's target port
    # is AVAILABLE, and weight 1 otherwise (docs/qos.md).
    ue: str = ""

    def __post_init__(self) -> None:
        _require(not self.ue or UAV_ID_PATTERN.fullmatch(self.ue) is not None, "ue", "must be a drone id")
        _require(
            bool(self.name) and self.name.replace("-", "").replace("_", "").isalnum(),
            "name",
            "must be letters, digits, - or _",
        )
        _host_port(self.target, "target")

    @property
    def target_host_port(self) -> tuple[str, int]:
        return _host_port(self.target, "target")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class BackgroundConfig:
    """A virtual background user: it takes capacity at its offered rate; no bytes move."""

    name: str
    weight: Annotated[float, In(0, 1000, "must be in (0, 1000]", lo_open=True)] = 1.0
    offered_mbps: Annotated[float, In(0, 1e5, "must be in 0..100000")] = 0.0

    def __post_init__(self) -> None:
        _require(bool(self.name), "name", "must not be empty")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class CellEventConfig:
    """A timeline event; which fields it needs depends on `kind` (see docs/cell.md)."""

    at_s: Annotated[float, In(0, 86400, "must be in 0..86400 s")]
    kind: Literal[
        "background",
        "capacity",
        "trace",
        "coverage_loss",
        "downlink_loss",
        "weight",
        "qod_end",
        "qod_profile",
    ]
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
    # qod_profile: the operator changes one of its profiles: its status (ACTIVE, INACTIVE, or WITHDRAWN:
    # no longer listed) and, when > 0, its maxDuration
    profile: str = ""
    status: Literal["", "ACTIVE", "INACTIVE", "WITHDRAWN"] = ""
    max_duration_s: Annotated[int, In(0, 86400, "must be in 0..86400 s")] = 0

    def __post_init__(self) -> None:
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
        elif self.kind == "qod_profile":
            _require(bool(self.profile), "profile", "a qod_profile event names its profile")
            _require(
                bool(self.status) or self.max_duration_s > 0,
                "status",
                "a qod_profile event sets a status or a max_duration_s (or both)",
            )
        if self.kind == "trace":
            _require(self.mean_mbps >= 0, "mean_mbps", "must be >= 0")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class CellConfig:
    """The emulated 5G cell (docs/cell.md). `scale` divides every rate."""

    uplink_mbps: Annotated[float, In(0, 1e5, "must be in 0..100000")] = 81.3
    downlink_mbps: Annotated[float, In(0, 1e6, "must be in (0, 1000000]", lo_open=True)] = 1400.0
    tti_ms: Annotated[float, In(0.1, 100, "must be in 0.1..100 ms")] = 1.0
    base_delay_up_ms: Annotated[float, In(0, 10_000, "must be in 0..10000 ms")] = 10.0
    base_delay_down_ms: Annotated[float, In(0, 10_000, "must be in 0..10000 ms")] = 10.0
    jitter_ms: Annotated[float, In(0, 10_000, "must be in 0..10000 ms")] = 0.5
    scale: Annotated[float, In(0, 1e4, "must be in (0, 10000]", lo_open=True)] = 1.0
    ue_buffer_bytes: Annotated[int, In(1500, 1 << 30, "must be 1500..1 GiB")] = 1_000_000
    listen_host: str = "127.0.0.1"
    default_listen_port: Annotated[int, In(0, 65535, "must be 0..65535")] = 17447
    priority_listen_port: Annotated[int, In(0, 65535, "must be 0..65535")] = 17448
    priority_weight: Annotated[float, In(0, 1000, "must be in (0, 1000]", lo_open=True)] = 4.0
    record_interval_s: Annotated[float, In(0.01, 60, "must be in 0.01..60 s")] = 0.1
    control_port: Annotated[
        int, In(-1, 65535, "must be -1 (off), 0 (any) or a port")
    ] = -1  # -1: no control API; 0: any free port
    # The cell as an operator (docs/qos.md): with qod = true a drone's priority bearer gets its weight only
    # while a CAMARA Quality-on-Demand session grants it (the control port serves the QoD API); false is a
    # network with a static policy for the priority port (the `links` backend's assumption).
    qod: bool = False
    nef: bool = False  # serve the 3GPP NEF's AsSessionWithQoS too (with qod: sim/network/nef.py)
    nef_scs_as_ids: tuple[str, ...] = ()  # the SCS/AS ids the NEF serves (empty: any); others get a 403
    qod_max_sessions: Annotated[
        int, In(-1, math.inf, "must be -1 (no limit) or >= 0")
    ] = -1  # sessions AVAILABLE at once (-1: no limit; 0: the operator grants none)
    qod_setup_s: Annotated[float, In(0, 60, "must be in 0..60 s")] = (
        0.05  # REQUESTED -> AVAILABLE (or UNAVAILABLE when refused) after this long
    )
    qod_max_duration_s: Annotated[int, In(1, 10**7, "must be in 1..10000000 s")] = (
        86400  # a session's duration (with extensions) is capped here
    )
    # per profile, a cap of its own (its QoS Profiles API's maxDuration); the others have qod_max_duration_s
    qod_profile_max_duration_s: dict[str, int] = field(default_factory=dict)
    qod_profiles: tuple[str, ...] = ("QOS_E", "QOS_S", "QOS_M", "QOS_L")  # what the operator offers
    qod_inactive_profiles: tuple[str, ...] = ()  # listed by its QoS Profiles API as INACTIVE: no sessions
    # the QoD version it serves: 1.2.0 also takes applicationServer.ipAddresses (a list of addresses)
    qod_api_version: Literal["1.1.0", "1.2.0"] = "1.1.0"
    qod_auth: bool = False  # require OAuth2 client-credential tokens ([qos.camara] client_id/secret file)
    qod_token_ttl_s: Annotated[float, In(1, 86400, "must be in 1..86400 s")] = 3600.0
    # CAMARA QoS Booking 0.1.0 beside the QoD API (docs/radio.md): bookings overlapping in time at once
    booking_max_concurrent: Annotated[int, In(-1, 10**6, "must be -1 (no limit) or >= 0")] = -1
    trace: str = ""
    trace_mean_mbps: Annotated[float, In(0, math.inf, "must be >= 0")] = 0.0
    seed: int = 0
    bearers: tuple[BearerConfig, ...] = ()  # empty: the drone's two flows (see bearer_list)
    background: tuple[BackgroundConfig, ...] = (BackgroundConfig(name="bg"),)
    events: tuple[CellEventConfig, ...] = ()
    radio: RadioConfig = field(default_factory=RadioConfig)  # where each drone's radio comes from
    prediction: PredictionConfig = field(default_factory=PredictionConfig)  # what the operator predicts of it

    def __post_init__(self) -> None:
        _require(bool(self.listen_host), "listen_host", "must not be empty")
        for name, cap in self.qod_profile_max_duration_s.items():
            key = f"qod_profile_max_duration_s.{name}"
            _require(
                name in (*self.qod_profiles, *self.qod_inactive_profiles), key, "is not an offered profile"
            )
            _require(1 <= cap <= 10**7, key, "must be in 1..10000000 s")
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
            BearerConfig(
                name=f"{uav}-default",
                target=f"{host}:{zenoh.default_port}",
                listen_port=self.default_listen_port,
                weight=1.0,
                ue=uav,
            ),
            BearerConfig(
                name=f"{uav}-priority",
                target=f"{host}:{zenoh.priority_port}",
                listen_port=self.priority_listen_port,
                weight=self.priority_weight,
                ue=uav,
            ),
        )


SERIAL_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600, 1000000, 1500000)


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class VehicleSimConfig:
    """`dynqos sim vehicle`: the simulated quadrotor's MAVLink links (PX4 SITL's ports) and world."""

    host: str = "127.0.0.1"
    offboard_bind_port: Annotated[int, In(0, 65535, "must be 0..65535 (0: any free port)")] = 14580
    offboard_remote_port: Annotated[int, In(0, 65535, "must be 0..65535 (0: any free port)")] = 14540
    gcs_bind_port: Annotated[int, In(0, 65535, "must be 0..65535 (0: any free port)")] = 18570
    gcs_remote_port: Annotated[int, In(0, 65535, "must be 0..65535 (0: any free port)")] = 14550
    speed: Annotated[float, In(0.01, 100, "must be in 0.01..100 (x real time)")] = 1.0
    wind_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: Annotated[float, In(0, 10, "must be in 0..10 m/s")] = 0.0
    gust_tau_s: Annotated[float, In(0.05, 600, "must be in 0.05..600 s")] = 2.0  # the gusts' correlation time
    seed: int = 0
    # What it reports wanders from where it is, as PX4's estimator does in SIH (docs/simulator.md).
    position_noise_m: Annotated[float, In(0, 1, "must be in 0..1 m")] = 0.03  # per horizontal axis, std
    position_noise_tau_s: Annotated[float, In(0.05, 600, "must be in 0.05..600 s")] = 1.0
    takeoff_alt_m: Annotated[float, In(0.5, 100, "must be in 0.5..100 m")] = 2.5
    offboard_loss_s: Annotated[float, In(0.1, 60, "must be in 0.1..60 s (COM_OF_LOSS_T)")] = 1.0
    lockstep: bool = False  # advance 20 ms per answer from the offboard peer instead of real time
    world_file: str = ""  # TOML/JSON world for contact checks; "" = the default arena
    start_m: tuple[float, float] = (0.0, 0.0)  # where it stands before take-off (north, east), local NED
    # MAVLink 2 signing as PX4 does it with a key provisioned (sim/vehicle/mavlink.py); "" = off.
    signing_key: str = ""
    # The offboard link over a serial line instead of UDP (sim/vehicle/serial_link.py): "pty" makes a
    # pseudo-terminal pair (its path is in the ready line), a path opens that device; "" = UDP.
    offboard_serial: str = ""
    serial_baud: int = 921600
    serial_flow_control: bool = False  # RTS/CTS, on a real device

    def __post_init__(self) -> None:
        _require(all(abs(w) <= 30 for w in self.wind_mps), "wind_mps", "components must be within 30 m/s")
        _require(all(abs(c) <= 1e4 for c in self.start_m), "start_m", "must be within 10 km of the origin")
        _require(
            self.serial_baud in SERIAL_BAUDS,
            "serial_baud",
            f"must be one of {', '.join(map(str, SERIAL_BAUDS))}",
        )


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class MetricsConfig:
    """Prometheus metrics and a health endpoint of a long-running process (docs/observability.md)."""

    port: Annotated[int, In(0, 65535, "must be 0 (off) or a TCP port in 1..65535")] = (
        0  # /metrics and /healthz on this TCP port; 0 = off (the default, the drone's too)
    )
    host: str = "127.0.0.1"  # where they listen; 0.0.0.0 in a pod, so that Prometheus can scrape it
    stale_after_s: Annotated[float, In(1.0, 3600, "must be in 1..3600 s")] = (
        30.0  # /healthz answers 503 when the last health line is older than this
    )

    def __post_init__(self) -> None:
        _require(bool(self.host.strip()), "host", "must not be empty")
