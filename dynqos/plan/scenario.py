"""A scenario of the paper's experiment: what it flies, the cell it flies in, and the dynqos config that
runs it. Scenarios come as TOML files (`dynqos run FILE`, or the built-in ones in dynqos/scenarios/)."""

from __future__ import annotations

import importlib.util
import sys
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from dynqos.common.config import (
    ArbiterConfig,
    BackgroundConfig,
    BearerConfig,
    CamaraConfig,
    CellConfig,
    Config,
    DeviceConfig,
    DroneConfig,
    DroneMissionConfig,
    NefConfig,
    NefUeConfig,
    OnboardConfig,
    PlannerConfig,
    QosConfig,
    SupervisorConfig,
    VehicleSimConfig,
    ZenohConfig,
    build,
    overlaid,
    to_toml,
)
from dynqos.common.errors import ConfigError
from dynqos.common.keys import UAV_ID_PATTERN
from dynqos.plan.camera_sizing import camera_size_for, flight_views
from dynqos.plan.cells import with_radio
from dynqos.plan.faults import Fault
from dynqos.plan.offloaded import offloaded
from dynqos.sim.network.bearer import socket_buffer_bytes

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_SCENARIOS = ("baseline", "bg-noqos", "bg-dynqos", "bg-staticqos")
UAV = "uav1"  # the drone every scenario flies
UAV_PHONE_NUMBER = "+46700000001"  # its identity on the emulated operator's network (a test range)
QOD_DURATION_S = 30  # each QoD session is asked for this long, and extended while still wanted
MAX_FLEET = 16


@dataclass(frozen=True, slots=True, kw_only=True)
class FleetDrone:
    """[[scenario.drones]]: one drone of a fleet, its mission and the risk zone it flies in."""

    id: str
    risk_zone: Literal["high", "low"]  # what the world puts in front of its camera (docs/fleet.md)
    center_m: tuple[float, float]
    mission: Literal["circle", "hover", "figure8"] = "circle"
    radius_m: float = 2.0
    period_s: float = 12.0
    yaw: Literal["tangent", "fixed", "center"] = "center"  # center: the camera faces the circle's centre

    def __post_init__(self) -> None:
        if UAV_ID_PATTERN.fullmatch(self.id) is None:
            raise ConfigError("id", "1 to 32 characters from A-Z a-z 0-9 _ -")
        DroneMissionConfig(mission=self.mission, radius_m=self.radius_m, period_s=self.period_s)

    def mission_config(self) -> DroneMissionConfig:
        return DroneMissionConfig(
            mission=self.mission,
            center_m=self.center_m,
            radius_m=self.radius_m,
            period_s=self.period_s,
            yaw=self.yaw,
        )

    @property
    def start_m(self) -> tuple[float, float]:
        """Where it stands before take-off: where its mission starts (never inside what it circles)."""
        if self.mission == "hover":
            return self.center_m
        offset = self.radius_m if self.mission == "circle" else 0.0
        return (self.center_m[0] + offset, self.center_m[1])


@dataclass(frozen=True, slots=True, kw_only=True)
class Scenario:
    name: str
    description: str = ""
    mission: Literal["circle", "hover", "figure8"] = "circle"
    qos: Literal["dynamic", "default", "priority"] = "dynamic"
    duration_s: float = 30.0  # flight time recorded after offloading starts
    bg_start_s: float = 15.0  # seconds into the recorded flight; negative: no background load
    bg_mbps: float = 80.0
    uav_mbps: float = 47.0  # what the drone's camera is sized to offer (before scale)
    scale: float = 10.0
    seed: int = 0
    metrics_port: int = 0  # each process's Prometheus /metrics on this port and the next ones (0: off)
    settle_s: float = 4.0  # excluded from the baseline statistics after offloading starts
    camera_fps: float = 15.0
    # The camera's bytes are paced at this rate (before scale; 0: each image in one burst): above what
    # the drone offers, below what the priority bearer drains under load (81.3 x 4/5 = 65 Mbit/s).
    camera_pace_mbps: float = 62.0
    priority_weight: float = 4.0  # the priority bearer's scheduling weight against 1 for everyone else
    # How the network gives the priority flow its weight (docs/qos.md): camara, the emulated cell grants it
    # only while a QoD session the QoS agent asked for is AVAILABLE (the truer model of the paper's
    # network); links, by static policy for the priority port, the moment the drone uses it.
    # nef: the same, asked of the emulated 5G core's NEF (AsSessionWithQoS) instead of its QoD API.
    qos_backend: Literal["links", "camara", "nef"] = "camara"
    base_delay_ms: float = 5.0  # one way: with processing and camera head-of-line ~15 ms C&C RTT, below rho2
    faults: tuple[
        Fault, ...
    ] = ()  # injected during the flight (dynqos/experiment/faults.py, docs/reliability.md)
    memory_sample_s: float = 5.0  # how often each process's resident memory is recorded
    # The supervisor's settings ([scenario.supervisor]; a profile replaces them,
    # dynqos/experiment/profile.py); its seed is the scenario's.
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    profile: str = "dynqos"  # the profile applied (dynqos/profiles/), named in the summary
    # A fleet (docs/fleet.md): several drones in one cell; empty, the one drone uav1 flies `mission`.
    # uav_mbps is then what each drone offers.
    drones: tuple[FleetDrone, ...] = ()
    world: str = ""  # a built-in world (dynqos/worlds/<name>.toml) or a world file; "": the default arena
    qos_policy: Literal["grant-all", "arbiter"] = "grant-all"  # who of the fleet gets priority
    arbiter_max_grants: int = -1  # the arbiter's budget: at most this many drones at once (-1: none)
    bg_weight: float = 1.0  # the background user's scheduling weight (a busy cell: several users' worth)
    # MPC and planner processes (docs/reliability.md, "Replicated MPC"): named mpc, mpc-1, ... and
    # planner, planner-1, ... (their replica ids)
    mpc_replicas: int = 1
    planner_replicas: int = 1
    # QoS agents (docs/qos.md, "Several agents"): qos, qos-1, ...; one active, the others standing by.
    # With more than one, no agent takes the operator's notifications (they would share one address):
    # each polls its sessions.
    qos_agents: int = 1
    # Edge sites (docs/multipath.md): 2 starts a second cell and a second site (router linked to the
    # first, MPC, planner, QoS agent, detector), and the drone holds a path through each cell to its site.
    sites: int = 1
    # Any dynqos setting ([scenario.config.<section>], as a config file writes it), over what the scenario
    # derives: the fields above are the experiment's own variables (each sets several settings, is
    # scaled, or is what reports and profiles compare); everything else is a setting (docs/demo.md).
    config: dict[str, Any] = field(default_factory=dict)
    # `dynqos edge ros2` beside the edge services (docs/ros2.md): the drones' ROS 2 topics on the router,
    # and ROS 2 nodes may steer them. Needs the ros2 extra.
    ros2_bridge: bool = False
    # Who flies: dynqos's simulated vehicle, or a real PX4 SITL from [px4] dir ([scenario.config.px4],
    # or `dynqos demo --vehicle px4 --px4-dir DIR`; docs/px4.md), one instance per drone.
    vehicle: Literal["sim", "px4"] = "sim"
    # The user's offloaded tasks (docs/offload.md): modules defining EDGE and ONBOARD; each EDGE is served
    # beside the edge services (a process task-<name>), each ONBOARD runs in every drone
    tasks: tuple[str, ...] = ()

    @property
    def run_id(self) -> str:
        return run_id(self.name, self.profile)

    def __post_init__(self) -> None:
        if not 5 <= self.duration_s <= 3600:
            raise ConfigError("duration_s", "must be in 5..3600 s")
        if self.bg_start_s >= self.duration_s:
            raise ConfigError("bg_start_s", "must be before the end of the run (or negative for none)")
        if not 0 <= self.bg_mbps <= 1e5 or not 0.1 <= self.uav_mbps <= 1e5:
            raise ConfigError("bg_mbps", "rates must be in 0..100000 Mbit/s")
        if not 0.01 <= self.scale <= 1000:
            raise ConfigError("scale", "must be in 0.01..1000")
        if not 0.1 <= self.priority_weight <= 100:
            raise ConfigError("priority_weight", "must be in 0.1..100")
        if not 0 <= self.camera_pace_mbps <= 1e5:
            raise ConfigError("camera_pace_mbps", "must be in 0..100000 Mbit/s (0: no pacing)")
        for i, fault in enumerate(self.faults):
            if fault.at_s + fault.duration_s > self.duration_s:
                raise ConfigError(f"faults[{i}].at_s", "the fault must end before the run does")
        self._check_run()
        self._check_fleet()
        try:
            overlaid(Config(), self.config)  # a setting that does not exist or fit is an error now
        except ConfigError as exc:
            raise exc.under("config") from None

    def _check_run(self) -> None:
        for name in ("mpc_replicas", "planner_replicas", "qos_agents"):
            if not 1 <= getattr(self, name) <= MAX_REPLICAS:
                raise ConfigError(name, f"must be in 1..{MAX_REPLICAS}")
        for i, fault in enumerate(self.faults):
            needs = REPLICA_FAULTS.get(fault.kind)
            if needs is not None and getattr(self, needs) < 2:
                raise ConfigError(f"faults[{i}].kind", f"{fault.kind} needs {needs} >= 2 (a standby)")
        self._check_sites()
        offloaded(self.tasks)  # a task module that does not load stops the run here, in one line
        if self.ros2_bridge and importlib.util.find_spec("rosbags") is None:
            raise ConfigError("ros2_bridge", "needs the ros2 extra: pip install 'dynqos[ros2]'")
        if not 0.5 <= self.memory_sample_s <= 600:
            raise ConfigError("memory_sample_s", "must be in 0.5..600 s")
        if self.metrics_port and not 1024 <= self.metrics_port <= 65000:
            raise ConfigError(
                "metrics_port", "must be 0 (off) or a port in 1024..65000 (each process takes the next)"
            )
        self._check_fleet()

    def _check_sites(self) -> None:
        if self.sites not in (1, 2):
            raise ConfigError("sites", "1, or 2 for a drone on two paths (docs/multipath.md)")
        if self.sites == 2 and (self.qos_backend == "nef" or self.vehicle != "sim"):
            raise ConfigError(
                "sites", 'two sites fly simulated drones with qos_backend "links" or "camara" (for now)'
            )
        for i, fault in enumerate(self.faults):
            if (fault.site == "b" or fault.kind == "path_partition") and self.sites < 2:
                raise ConfigError(
                    f"faults[{i}].site", f"{'site b' if fault.site == 'b' else fault.kind} needs sites = 2"
                )

    def _check_fleet(self) -> None:
        if self.qos_policy == "arbiter" and self.qos_backend == "links":
            raise ConfigError("qos_policy", 'the arbiter needs qos_backend = "camara" or "nef"')
        if self.qos_backend == "nef" and (self.fleet or self.qos_agents != 1):
            # each agent listens for the NEF's notifications on a port of its own: not wired here yet
            raise ConfigError("qos_backend", '"nef" flies one drone with one QoS agent (for now)')
        ids = [d.id for d in self.drones]
        if len(set(ids)) != len(ids):
            raise ConfigError("drones", "drone ids must be unique")
        if len(self.drones) > MAX_FLEET:
            raise ConfigError("drones", f"at most {MAX_FLEET} drones on one machine")
        for i, fault in enumerate(self.faults if self.drones else ()):
            if fault.kind not in FLEET_FAULTS:
                raise ConfigError(
                    f"faults[{i}].kind",
                    f"a fleet scenario injects only "
                    f"{', '.join(FLEET_FAULTS)}: {fault.kind} acts on one drone's link or "
                    "flight controller",
                )
        if not 0.1 <= self.bg_weight <= 100:
            raise ConfigError("bg_weight", "must be in 0.1..100")
        if self.world:
            world_path(self.world)  # a name or file that is not there is an error now, not mid-run

    @property
    def fleet(self) -> bool:
        return bool(self.drones)

    @property
    def uavs(self) -> list[str]:
        return [d.id for d in self.drones] or [UAV]


MAX_REPLICAS = 8
# Scenario keys that were settings under another name, and the section that holds each now
MOVED = {
    "wind_mps": "vehicle",
    "gust_std_mps": "vehicle",
    "gust_tau_s": "vehicle",
    "qod_max_sessions": "cell",
    "camera_part_bytes": "onboard",
}
# the faults that act on the replica serving the drone, and the setting that must give it a standby
REPLICA_FAULTS = {
    "mpc_replica_kill": "mpc_replicas",
    "mpc_replica_hang": "mpc_replicas",
    "planner_replica_kill": "planner_replicas",
    "qos_agent_kill": "qos_agents",
    "qos_agent_hang": "qos_agents",
}


# the faults a fleet scenario may inject: they act on the edge's processes, a whole site, a whole cell or
# the link between the sites, and each replica fault on the replica serving the fleet's first drone
FLEET_FAULTS = (
    "mpc_replica_kill",
    "mpc_replica_hang",
    "planner_replica_kill",
    "qos_agent_kill",
    "qos_agent_hang",
    "replica_join",
    "background",
    "site_kill",
    "cell_outage",
    "path_partition",
    "task_kill",
)


def replica_names(service: str, count: int) -> list[str]:
    """A run's processes of an edge service, which are also their replica ids: mpc, mpc-1, mpc-2, ..."""
    return [service, *(f"{service}-{i}" for i in range(1, count))]


def world_path(world: str) -> str:
    """A built-in world's file (dynqos/worlds/<name>.toml) or the file named, as an absolute path."""
    builtin = resources.files("dynqos") / "worlds" / f"{world}.toml"
    if builtin.is_file():
        return str(Path(str(builtin)).resolve())
    path = Path(world)
    if not path.is_file():
        raise ConfigError("world", f"no built-in world {world!r} and no such file")
    return str(path.resolve())


def load_scenario(path: str | Path) -> Scenario:
    source = str(path)
    try:
        table = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("", "scenario file not found", source=source) from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError("", f"cannot read scenario ({exc})", source=source) from None
    unknown = set(table) - {"scenario"}
    if unknown or not isinstance(table.get("scenario"), dict):
        raise ConfigError(
            ", ".join(sorted(unknown)) or "scenario",
            "a scenario file has one [scenario] table",
            source=source,
        )
    for key, section in MOVED.items():
        if key in table["scenario"]:
            raise ConfigError(
                f"scenario.{key}",
                f"is a setting: write it as [scenario.config.{section}] {key}",
                source=source,
            )
    try:
        return build(Scenario, table["scenario"], "scenario")
    except ConfigError as exc:
        raise exc.with_source(source) from None


def builtin_names() -> list[str]:
    """The scenarios dynqos ships (dynqos/scenarios/*.toml), by name."""
    files = resources.files("dynqos") / "scenarios"
    return sorted(p.name.removesuffix(".toml") for p in files.iterdir() if p.name.endswith(".toml"))


def builtin_scenario(name: str) -> Scenario:
    path = resources.files("dynqos") / "scenarios" / f"{name}.toml"
    if not path.is_file():
        raise ConfigError("--scenario", f"unknown scenario {name!r} (known: {', '.join(builtin_names())})")
    with resources.as_file(path) as real:
        return load_scenario(real)


def run_id(name: str, profile: str) -> str:
    """A run folder's name (and a scenario's name in reports): the scenario's, and the profile's unless
    it is the default one."""
    return name if profile == "dynqos" else f"{name}@{profile}"


def scenario_config(scenario: Scenario, *, zenoh: ZenohConfig, fc_port: int, gcs_port: int) -> Config:
    """The dynqos config that flies `scenario` on one machine: every process on 127.0.0.1, the cell's
    bearers and control API on free ports (the cell reports them on its ready line), the simulator
    sending to the onboard daemon's `fc_port`, the camera sized to offer the scenario's rate from the
    views its mission flies (dynqos/plan/camera_sizing.py)."""
    config = Config(
        drone=DroneConfig(id=UAV),
        # The drone's send buffer on the bulk link is a queue in front of the cell like the UE buffer;
        # scaled with the rates it holds the same time at any scale (docs/demo.md, "Scaling").
        zenoh=replace(zenoh, bulk_sndbuf_bytes=socket_buffer_bytes(scenario.scale)),
        supervisor=replace(scenario.supervisor, seed=scenario.seed),
        cell=CellConfig(
            scale=scenario.scale,
            ue_buffer_bytes=max(1500, round(1_000_000 / scenario.scale)),
            base_delay_up_ms=scenario.base_delay_ms,
            base_delay_down_ms=scenario.base_delay_ms,
            control_port=0,
            default_listen_port=0,
            priority_listen_port=0,
            seed=scenario.seed,
            priority_weight=scenario.priority_weight,
            qod=scenario.qos_backend != "links",
            nef=scenario.qos_backend == "nef",
            background=(BackgroundConfig(name="bg", weight=scenario.bg_weight),),
        ),
        vehicle=VehicleSimConfig(
            # a steady breeze from the north, with short gusts, so that control delay shows in the
            # tracking and windows compare alike (docs/demo.md)
            wind_mps=(0.5, 0.0, 0.0),
            gust_std_mps=0.5,
            gust_tau_s=0.5,
            offboard_bind_port=0,
            gcs_bind_port=0,
            offboard_remote_port=fc_port,
            gcs_remote_port=gcs_port,
            seed=scenario.seed,
        ),
        planner=PlannerConfig(mission=scenario.mission, lead_in_s=2.0),
        onboard=OnboardConfig(
            mavlink_url=f"udpin:127.0.0.1:{fc_port}",
            qos=scenario.qos,
            camera_fps=scenario.camera_fps,
            camera_pace_mbps=scenario.camera_pace_mbps / scenario.scale,
            # a C&C message queued behind a paced part waits for it to drain at the drone's scaled
            # share: a fleet (a smaller share each) sets smaller parts (docs/fleet.md)
            camera_part_bytes=4096,
            # The heading stays the FC's own, as in every run the README quotes. Flown along the circle,
            # the camera sees the pillars for most of a lap (measured: the baseline in q2, high risk, 22
            # of 30 s) and the scenarios' contrast changes; docs/demo.md says more.
            yaw="free",
            tasks=tuple(o.onboard for o in offloaded(scenario.tasks)),
        ),
        # The QoS agent's api_root is the cell's control port, known once the cell is up (with_bearers).
        qos=QosConfig(
            backend=scenario.qos_backend,
            camara=CamaraConfig(
                api_root="http://127.0.0.1:1/quality-on-demand/v1",
                duration_s=QOD_DURATION_S,
                extend_before_s=QOD_DURATION_S / 3,
                retry_after_denied_s=5.0,
                devices={UAV: DeviceConfig(phoneNumber=UAV_PHONE_NUMBER)},
            ),
            nef=NefConfig(  # the same UE, known to the core by its GPSI
                api_root="http://127.0.0.1:1",
                notification_destination="http://127.0.0.1:1/nef-events",
                sink_listen="127.0.0.1:1",
                retry_after_denied_s=5.0,
                ues={UAV: NefUeConfig(gpsi=f"msisdn-{UAV_PHONE_NUMBER.lstrip('+')}")},
                # the core's delay reports, every second, for a supervisor that reads them
                qos_monitoring=scenario.supervisor.network_aware,
            ),
        ),
    )
    config = with_radio(overlaid(config, scenario.config))
    part_bytes = config.onboard.camera_part_bytes if scenario.camera_pace_mbps > 0 else 0
    target_bps = scenario.uav_mbps * 1e6 / scenario.scale
    width, height = camera_size_for(target_bps, scenario.camera_fps, flight_views(config), part_bytes)
    return replace(config, onboard=replace(config.onboard, camera_width=width, camera_height=height))


def phone_number(index: int) -> str:
    """The i-th drone's identity on the emulated operator's network (a test range)."""
    return f"+4670000{index + 1:04d}"


def fleet_configs(
    scenario: Scenario, *, zenoh: ZenohConfig, fc_base: int, gcs_port: int
) -> tuple[Config, dict[str, Config]]:
    """The edge's config (one cell with a pair of bearers per drone, the planner's per-drone missions,
    the QoS agent's policy and devices) and each drone's: its id, its vehicle (`--instance i`: system
    id i + 1, offboard port fc_base + i), where it spawns, and a camera sized to offer uav_mbps from
    the views of its own mission."""
    shared = scenario_config(scenario, zenoh=zenoh, fc_port=fc_base, gcs_port=gcs_port)
    world = world_path(scenario.world) if scenario.world else ""
    bearers = tuple(
        BearerConfig(name=f"{d.id}-{flow}", target=f"{zenoh.edge_host}:{port}", weight=weight, ue=d.id)
        for d in scenario.drones
        for flow, port, weight in (
            ("default", zenoh.default_port, 1.0),
            ("priority", zenoh.priority_port, scenario.priority_weight),
        )
    )
    devices = {d.id: DeviceConfig(phoneNumber=phone_number(i)) for i, d in enumerate(scenario.drones)}
    shared = replace(
        shared,
        cell=replace(shared.cell, bearers=bearers),
        planner=replace(shared.planner, drones={d.id: d.mission_config() for d in scenario.drones}),
        vehicle=replace(shared.vehicle, world_file=world),
        onboard=replace(shared.onboard, world_file=world, yaw="command"),
        qos=replace(
            shared.qos,
            policy=scenario.qos_policy,
            arbiter=ArbiterConfig(max_grants=scenario.arbiter_max_grants),
            camara=replace(shared.qos.camara, devices=devices),
        ),
    )
    shared = with_radio(shared)
    part_bytes = shared.onboard.camera_part_bytes if scenario.camera_pace_mbps > 0 else 0
    target_bps = scenario.uav_mbps * 1e6 / scenario.scale
    drones: dict[str, Config] = {}
    for i, d in enumerate(scenario.drones):
        config = replace(
            shared,
            drone=DroneConfig(id=d.id),
            vehicle=replace(shared.vehicle, start_m=d.start_m, seed=scenario.seed + i),
            onboard=replace(shared.onboard, mavlink_url=f"udpin:127.0.0.1:{fc_base + i}", fc_system_id=i + 1),
        )
        views = flight_views(config)
        width, height = camera_size_for(target_bps, scenario.camera_fps, views, part_bytes, world)
        drones[d.id] = replace(
            config, onboard=replace(config.onboard, camera_width=width, camera_height=height)
        )
    return shared, drones


def write_config(path: Path, scenario: Scenario, config: Config) -> None:
    path.write_text(f"# generated by dynqos demo for scenario {scenario.name}\n" + to_toml(config))
