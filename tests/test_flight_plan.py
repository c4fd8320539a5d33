"""Every shipped scenario's plan, read without flying it: which processes start, in which stage, with
which config and priority, and what happens at which second (dynqos/plan/flight.py)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from dynqos.common.messages import State
from dynqos.experiment.flight_configs import config_paths, flight_configs, write_configs
from dynqos.experiment.sites import with_site_b
from dynqos.plan.flight import NICE, SHARED, SITE_B, FlightPlan, Launch, config_file, plan_flight
from dynqos.plan.offloaded import offloaded
from dynqos.plan.recording import FlightRecords
from dynqos.plan.scenario import Scenario, load_scenario, replica_names

SCENARIOS = sorted(
    p.name.removesuffix(".toml")
    for p in (resources.files("dynqos") / "scenarios").iterdir()
    if p.name.endswith(".toml")
)
FOLDER = Path("/runs/flight")


def shipped(name: str) -> Scenario:
    return load_scenario(Path(str(resources.files("dynqos") / "scenarios" / f"{name}.toml")))


def names(launches: tuple[Launch, ...]) -> list[str]:
    return [launch.name for launch in launches]


def site_a_services(scenario: Scenario) -> list[str]:
    return [
        *replica_names("qos", scenario.qos_agents),
        *replica_names("planner", scenario.planner_replicas),
        *replica_names("mpc", scenario.mpc_replicas),
        "detector",
        *(task.process for task in offloaded(scenario.tasks)),
    ]


def test_every_shipped_scenario_is_planned() -> None:
    assert len(SCENARIOS) >= 28
    assert {"baseline", "faults", "fleet-arbiter", "dual-homed", "fleet-dual-homed"} <= set(SCENARIOS)


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_plan_starts_each_service_once_in_its_stage(name: str) -> None:
    scenario = shipped(name)
    plan = plan_flight(scenario, FOLDER)
    every = names(plan.launches())
    assert len(every) == len(set(every)), every
    assert names(plan.network)[:2] == ["router", "cell"]
    assert plan.named("cell").args == ("sim", "cell", "--out", str(FOLDER))
    edge = names(plan.edge)
    for service in site_a_services(scenario):
        assert service in edge, service
    for replica in replica_names("mpc", scenario.mpc_replicas):
        assert plan.named(replica).args == ("edge", "mpc", "--set", f'mpc.replica_id="{replica}"')
    assert plan.drones == tuple(scenario.uavs)
    assert not plan.vehicles  # dynqos's vehicles start with the edge
    if scenario.drones:
        _a_fleet(scenario, plan)
    else:
        _one_drone(scenario, plan)
    if scenario.sites == 2:
        _two_sites(scenario, plan)
    else:
        assert not any(launch.config == SITE_B for launch in plan.launches())


def _a_fleet(scenario: Scenario, plan: FlightPlan) -> None:
    """Each drone has its vehicle and daemon on its own config; best-effort work runs niced; no recorder
    of the whole flight (a fifth subscriber of every state on two cores)."""
    for i, uav in enumerate(scenario.uavs):
        vehicle = plan.named(f"vehicle-{uav}")
        assert vehicle.config == uav
        assert vehicle.args[:4] == ("sim", "vehicle", "--instance", str(i))
        assert plan.named(f"onboard-{uav}").config == uav
    assert names(plan.onboard) == [f"onboard-{uav}" for uav in scenario.uavs]
    assert "record" not in names(plan.launches())
    assert plan.named("detector").nice == NICE
    planned = bool(scenario.config.get("fleet_plan", {}).get("tasks"))
    assert ("fleet-planner" in names(plan.edge)) == planned
    if planned:
        assert plan.named("fleet-planner").nice == NICE
    for control in (*replica_names("mpc", scenario.mpc_replicas), *replica_names("qos", scenario.qos_agents)):
        assert plan.named(control).nice == 0


def _one_drone(scenario: Scenario, plan: FlightPlan) -> None:
    assert names(plan.onboard) == ["onboard"]
    assert plan.named("onboard").config == SHARED
    assert plan.named("vehicle").args == ("sim", "vehicle", "--instance", "0", "--duration", "3600")
    record = plan.named("record")
    assert record.args[:3] == ("record", "--out", str(FOLDER / "flight.mcap"))
    assert "--no-camera" in record.args
    assert all(launch.nice == 0 for launch in plan.launches())


def _two_sites(scenario: Scenario, plan: FlightPlan) -> None:
    """Site B: its router and cell from its own config, and a twin of each of site A's services."""
    assert names(plan.network) == ["router", "cell", "router-b", "cell-b"]
    assert plan.named("cell-b").args[-1] == str(FOLDER / "site-b")
    stage = plan.after_edge if scenario.drones else plan.edge
    for service in site_a_services(scenario):
        twin = plan.named(f"{service}-b")
        assert twin.config == SITE_B
        assert twin.name in names(stage)
    assert plan.named("mpc-b").args[-1] == 'mpc.replica_id="mpc-b"'


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_timeline_is_the_load_and_the_faults_in_order(name: str) -> None:
    scenario = shipped(name)
    plan = plan_flight(scenario, FOLDER)
    times = [event.at_s for event in plan.timeline]
    assert times == sorted(times)
    faults = [e for e in plan.timeline if e.what != "load"]
    assert len(faults) == len(scenario.faults)
    loads = [e.at_s for e in plan.timeline if e.what == "load"]
    assert loads == ([scenario.bg_start_s] if scenario.bg_start_s >= 0 else [])
    assert all(0 <= e.at_s < plan.duration_s for e in plan.timeline)


def test_the_faults_flight_kills_the_mpc_at_6_s_and_the_router_at_54_s() -> None:
    plan = plan_flight(shipped("faults"), FOLDER)
    at = {event.what: event.at_s for event in plan.timeline}
    assert at["mpc_kill"] == 6
    assert at["detector_flood"] == 44
    assert at["router_kill"] == 54
    assert "load" not in at  # no background load in the faults flight


def test_a_fleet_on_px4_boots_its_instances_one_at_a_time_before_the_edge() -> None:
    scenario = shipped("fleet-arbiter")
    plan = plan_flight(scenario, FOLDER, px4=[3, 4, 5, 6])
    assert names(plan.vehicles) == [f"vehicle-{uav}" for uav in scenario.uavs]
    assert not any(name.startswith("vehicle") for name in names(plan.edge))
    first = plan.vehicles[0]
    assert first.args[:6] == ("sim", "px4", "--instance", "3", "--workdir", str(FOLDER / "px4" / "i3"))
    assert first.args[6] == "--start={},{}".format(*scenario.drones[0].start_m)
    assert first.timeout_s == 90


def test_one_drone_on_px4_starts_its_instance_with_the_edge() -> None:
    plan = plan_flight(shipped("bg-dynqos"), FOLDER, px4=[2])
    assert not plan.vehicles
    vehicle = plan.named("vehicle")
    assert vehicle in plan.edge
    assert vehicle.args == (
        "sim",
        "px4",
        "--instance",
        "2",
        "--workdir",
        str(FOLDER / "px4" / "i2"),
        "--start=0.0,0.0",
    )


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_config_the_plan_names_is_written_and_each_drone_flies_its_own(
    name: str, tmp_path: Path
) -> None:
    """One function writes the configs of one drone and of a fleet: one drone flies the run's config,
    each drone of a fleet its own (its id, its offboard port); site B's is there with two sites."""
    scenario = shipped(name)
    plan = plan_flight(scenario, tmp_path)
    configs = flight_configs(scenario, plan, tmp_path, None)
    if scenario.sites == 2:
        configs = with_site_b(configs, 0)
    assert {launch.config for launch in plan.launches()} <= set(configs)
    keys = plan.drone_configs()
    assert keys == (tuple(scenario.uavs) if scenario.fleet else (SHARED,))
    flown = [configs[key] for key in keys]
    assert [c.drone.id for c in flown] == list(plan.drones)
    ports = [c.onboard.mavlink_url for c in flown]
    assert len(set(ports)) == len(ports), ports  # each drone's vehicle sends to its own port
    if scenario.sites == 2:
        link = configs[SITE_B].zenoh.router_links
        assert link == (f"tcp/127.0.0.1:{configs[SHARED].zenoh.default_port}",)
    write_configs(config_paths(tmp_path, configs), scenario, configs)
    assert sorted(p.name for p in tmp_path.glob("*.toml")) == sorted(
        config_file(tmp_path, k).name for k in configs
    )


def test_one_drone_s_recording_is_the_flight_s_and_a_fleet_s_drones_keep_theirs() -> None:
    one = FlightRecords.of(("uav1",), fleet=False)
    assert one.drones["uav1"] is one.flight
    fleet = FlightRecords.of(("uav1", "uav2"), fleet=True)
    assert fleet.drones["uav1"] is not fleet.flight
    assert fleet.drones["uav1"] is not fleet.drones["uav2"]


def test_a_fleet_s_drone_is_recorded_from_the_flight_s_time_zero(tmp_path: Path) -> None:
    """The drones that offloaded first were heard before the last one did: those states are not the
    flight's."""
    records = FlightRecords.of(("uav1", "uav2"), fleet=True)
    records.flight.t0_ns, records.flight.bg_on_ns = 5_000, 9_000
    early, late = hovering(stamp_ns=4_999), hovering(stamp_ns=5_000)
    records.drones["uav1"].states = [(1.0, early), (2.0, late)]
    records.on_flight_clock("uav1")
    drone = records.drones["uav1"]
    assert drone.states == [(2.0, late)]
    assert (drone.t0_ns, drone.bg_on_ns, drone.faults) == (5_000, 9_000, records.flight.faults)


def hovering(stamp_ns: int) -> State:
    zero = (0.0, 0.0, 0.0)
    return State(uav="uav1", seq=1, stamp_ns=stamp_ns, pos_m=zero, vel_mps=zero, quat=(1.0, 0.0, 0.0, 0.0))
