"""A flight as data: every process a scenario starts, in which stage, with which config and at which
priority, and what happens when, decided before anything starts.

One drone is a fleet of one: the runner (experiment/runner.py) starts the stages this plan names, in
its order, for one drone and for a fleet, and where the two differ (a recorder of the whole flight for
one drone; in a fleet the detector, the fleet planner and the ROS 2 face below the control path, each
drone's own config file, and PX4 instances booted one at a time) the difference is here, as data.
A test reads the plan of every shipped scenario without flying it (tests/test_flight_plan.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dynqos.plan.offloaded import offloaded
from dynqos.plan.scenario import Scenario, replica_names, world_path

SHARED = ""  # a Launch's config: the run's dynqos.toml
SITE_B = "b"  # site B's dynqos-b.toml; any other value is a fleet drone's id: that drone's <id>.toml
NICE = 10  # best-effort work on a machine the control path shares runs this much below it
MCAP_NAME = "flight.mcap"
PX4_FOLDER = "px4"  # the run folder's sub-folder of PX4's working directories (its ULogs among them)
SITE_B_FOLDER = "site-b"  # cell B's records, beside site A's
VEHICLE_RUNS_S = "3600"  # dynqos's vehicle runs until it is stopped; this bounds it


@dataclass(frozen=True)
class Launch:
    """One process: `dynqos ARGS --config FILE`, niced when `nice`, its log logs/<name>.log."""

    name: str
    args: tuple[str, ...]
    config: str = SHARED
    nice: int = 0
    timeout_s: float = 30.0  # until its ready line


@dataclass(frozen=True)
class Event:
    """What the flight does at `at_s` seconds into the recorded flight: the background load comes on
    (`load`, for the rest of the flight) or a fault begins (its kind, for `duration_s`)."""

    at_s: float
    what: str
    duration_s: float = 0.0
    site: str = "a"


@dataclass(frozen=True)
class FlightPlan:
    """The stages in start order. `network` and `edge` start together (each process needs only what the
    stages before it started); `vehicles`, `after_edge` and `onboard` one at a time, and each drone's
    daemon is waited for until its drone offloads before the next starts."""

    scenario: str
    drones: tuple[str, ...]
    network: tuple[Launch, ...]
    vehicles: tuple[Launch, ...]
    edge: tuple[Launch, ...]
    after_edge: tuple[Launch, ...]
    onboard: tuple[Launch, ...]
    timeline: tuple[Event, ...]
    duration_s: float

    def launches(self) -> tuple[Launch, ...]:
        return self.network + self.vehicles + self.edge + self.after_edge + self.onboard

    def drone_configs(self) -> tuple[str, ...]:
        """Each drone's config, in `drones`' order: SHARED for one drone (it flies the run's config), the
        drone's id in a fleet (its own file)."""
        return tuple(item.config for item in self.onboard)

    def named(self, name: str) -> Launch:
        for launch in self.launches():
            if launch.name == name:
                return launch
        raise KeyError(name)


def plan_flight(scenario: Scenario, folder: Path, px4: list[int] | None = None) -> FlightPlan:
    """The plan of `scenario` flown into `folder`; `px4`: the PX4 instance of each drone (None: dynqos's
    simulated vehicles fly)."""
    fleet = bool(scenario.drones)
    drones = tuple(scenario.uavs)
    vehicles = _vehicles(scenario, folder, px4)
    boot_alone = fleet and px4 is not None  # PX4 instances of a fleet boot one at a time
    edge = [
        *_replicas(scenario, "qos", scenario.qos_agents),
        *([] if fleet else [_recorder(scenario, folder)]),
        *([] if boot_alone else vehicles),
        *_replicas(scenario, "planner", scenario.planner_replicas),
        *_replicas(scenario, "mpc", scenario.mpc_replicas),
        *_edge_services(scenario, best_effort=NICE if fleet else 0),
    ]
    site_b = _site_b(scenario) if scenario.sites == 2 else []
    return FlightPlan(
        scenario=scenario.name,
        drones=drones,
        network=_network(scenario, folder),
        vehicles=tuple(vehicles) if boot_alone else (),
        edge=tuple(edge + ([] if fleet else site_b)),
        after_edge=tuple(site_b if fleet else []),
        onboard=tuple(Launch(f"onboard-{uav}", ("onboard", "--takeoff"), config=uav) for uav in drones)
        if fleet
        else (Launch("onboard", ("onboard", "--takeoff")),),
        timeline=timeline(scenario),
        duration_s=scenario.duration_s,
    )


def config_file(folder: Path, key: str) -> Path:
    """Where the config a Launch names is written: the run's dynqos.toml, site B's dynqos-b.toml, a fleet
    drone's <id>.toml."""
    if key == SHARED:
        return folder / "dynqos.toml"
    return folder / ("dynqos-b.toml" if key == SITE_B else f"{key}.toml")


def px4_workdir(folder: Path, instance: int) -> Path:
    """PX4 instance `instance`'s working directory in the run folder (its ULogs among its files)."""
    return folder / PX4_FOLDER / f"i{instance}"


def site_b_folder(folder: Path) -> Path:
    """Where cell B writes its records (cell.csv, qod.json): beside site A's, in their own folder."""
    return folder / SITE_B_FOLDER


def timeline(scenario: Scenario) -> tuple[Event, ...]:
    """The load and the faults, in the order they happen."""
    events = [Event(f.at_s, f.kind, f.duration_s, f.site) for f in scenario.faults]
    if scenario.bg_start_s >= 0:
        events.append(Event(scenario.bg_start_s, "load"))
    return tuple(sorted(events, key=lambda e: e.at_s))


def _network(scenario: Scenario, folder: Path) -> tuple[Launch, ...]:
    network = [Launch("router", ("edge", "router")), Launch("cell", ("sim", "cell", "--out", str(folder)))]
    if scenario.sites == 2:
        network += [
            Launch("router-b", ("edge", "router"), config=SITE_B),
            Launch("cell-b", ("sim", "cell", "--out", str(site_b_folder(folder))), config=SITE_B),
        ]
    return tuple(network)


def _replicas(scenario: Scenario, service: str, count: int, site: str = "") -> list[Launch]:
    """An edge service's processes, each named by its replica id (site B's with -b after it)."""
    launches = []
    for name in replica_names(service, count):
        name = f"{name}-{site}" if site else name
        args = ("edge", service, "--set", f'{service}.replica_id="{name}"')
        launches.append(Launch(name, args, config=SITE_B if site else SHARED))
    return launches


def _recorder(scenario: Scenario, folder: Path) -> Launch:
    """`dynqos record` of the whole flight, without the camera images (it runs niced by itself). Not in
    a fleet: four drones take this 2-core machine to its limit, and a fifth subscriber of every state
    perturbed the fleet's figures in CI (docs/observability.md)."""
    args = ["record", "--out", str(folder / MCAP_NAME), "--scenario", scenario.name, "--no-camera"]
    if scenario.world:
        args += ["--world", world_path(scenario.world)]
    return Launch("record", tuple(args))


def _vehicles(scenario: Scenario, folder: Path, px4: list[int] | None) -> list[Launch]:
    """Each drone's vehicle: dynqos's simulated vehicle `--instance i`, or PX4 instance px4[i] with its
    working directory in the run folder, standing where the drone's mission starts."""
    fleet = bool(scenario.drones)
    launches = []
    for i, uav in enumerate(scenario.uavs):
        name, config = (f"vehicle-{uav}", uav) if fleet else ("vehicle", SHARED)
        if px4 is None:
            sim = ("sim", "vehicle", "--instance", str(i), "--duration", VEHICLE_RUNS_S)
            launches.append(Launch(name, sim, config=config))
            continue
        start_m = scenario.drones[i].start_m if fleet else (0.0, 0.0)
        workdir = px4_workdir(folder, px4[i])
        start = "--start={},{}".format(*start_m)  # one word: a start of -5.5 is no option
        sitl = ("sim", "px4", "--instance", str(px4[i]), "--workdir", str(workdir), start)
        launches.append(Launch(name, sitl, config=config, timeout_s=90.0))
    return launches


def _edge_services(scenario: Scenario, best_effort: int) -> list[Launch]:
    """The fleet planner (for a planned mission), the detector, each user task's service and the ROS 2
    face. The planner's burst of planning, the detector (it drops the frames it cannot keep up with)
    and the ROS 2 face are best effort: `best_effort` is their nice value."""
    launches = []
    if scenario.config.get("fleet_plan", {}).get("tasks"):
        launches.append(Launch("fleet-planner", ("edge", "fleet-planner"), nice=best_effort))
    launches.append(Launch("detector", ("edge", "detector"), nice=best_effort))
    launches += [Launch(t.process, ("edge", "serve", t.edge)) for t in offloaded(scenario.tasks)]
    if scenario.ros2_bridge:
        launches.append(Launch("ros2", ("edge", "ros2"), nice=best_effort))
    return launches


def _site_b(scenario: Scenario) -> list[Launch]:
    """Site B's QoS agents, planners, MPCs, detector and task services, as many as site A's."""
    launches = [
        *_replicas(scenario, "qos", scenario.qos_agents, SITE_B),
        *_replicas(scenario, "planner", scenario.planner_replicas, SITE_B),
        *_replicas(scenario, "mpc", scenario.mpc_replicas, SITE_B),
        Launch("detector-b", ("edge", "detector"), config=SITE_B),
    ]
    for task in offloaded(scenario.tasks):  # a replica of each user task's service at site B too
        name = f"{task.process}-b"
        launches.append(Launch(name, ("edge", "serve", task.edge, "--replica-id", name), config=SITE_B))
    return launches
