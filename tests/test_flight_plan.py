"""Every shipped scenario's plan, read without flying it: which processes start, in which stage, with
which config and priority, and what happens at which second (dynqos/plan/flight.py)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest

from dynqos.plan.flight import NICE, SHARED, SITE_B, FlightPlan, Launch, plan_flight
from dynqos.plan.offloaded import offloaded
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
