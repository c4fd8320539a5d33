"""The config files a flight writes, keyed as its plan names them (dynqos/plan/flight.py): the run's
(SHARED), site B's (SITE_B) and, in a fleet, each drone's (its id). One drone flies the run's config, a
fleet's drones their own; every process is on 127.0.0.1, on free ports."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from dynqos.common.config import Config, ZenohConfig
from dynqos.experiment.processes import flow_ports, free_udp_block
from dynqos.experiment.vehicles import with_px4
from dynqos.plan.flight import SHARED, FlightPlan, config_file
from dynqos.plan.scenario import Scenario, fleet_configs, scenario_config, write_config


def flight_configs(
    scenario: Scenario, plan: FlightPlan, folder: Path, px4: list[int] | None
) -> dict[str, Config]:
    """Each config of `plan` before anything starts (the cells' ports are added once they are up):
    each drone's vehicle sends to its own offboard port (a block of free UDP ports, the ground
    station's after them), its daemon flown by PX4 instance px4[i] where PX4 flies; a fleet's planned
    mission writes its plan into the run folder."""
    n = len(plan.drones)
    udp = free_udp_block(n + 1)  # each drone's offboard port, then the ground station's
    zenoh = ZenohConfig(**flow_ports())
    if scenario.fleet:
        shared, drones = fleet_configs(scenario, zenoh=zenoh, fc_base=udp, gcs_port=udp + n)
        configs = {SHARED: shared, **drones}
    else:
        configs = {SHARED: scenario_config(scenario, zenoh=zenoh, fc_port=udp, gcs_port=udp + 1)}
    configs = with_px4(configs, plan.drone_configs(), px4)
    shared = configs[SHARED]
    if shared.fleet_plan.tasks:  # the fleet's plan: for these drones, into the run folder
        fleet_plan = replace(shared.fleet_plan, drones=plan.drones, plan_file=str(folder / "plan.json"))
        configs[SHARED] = replace(shared, fleet_plan=fleet_plan)
    return configs


def config_paths(folder: Path, configs: dict[str, Config]) -> dict[str, Path]:
    """Where each of `configs` is written in the run folder (plan/flight.py's config_file)."""
    return {key: config_file(folder, key) for key in configs}


def write_configs(paths: dict[str, Path], scenario: Scenario, configs: dict[str, Config]) -> None:
    for key, config in configs.items():
        write_config(paths[key], scenario, config)
