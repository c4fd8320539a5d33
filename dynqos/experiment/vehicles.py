"""Who flies a scenario's drone: dynqos's simulated vehicle (`dynqos sim vehicle`) or a real PX4 SITL
(`dynqos sim px4`, sim/vehicle/px4_sitl.py). Either is the process named "vehicle" in the run, so faults
and logs find it the same way; what differs is where the onboard daemon listens. PX4 keeps its own
ports, so the daemon listens where PX4 instance N sends (14540+N) and reads system id N+1."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.config import Config
from dynqos.experiment.processes import Processes
from dynqos.experiment.scenario import Scenario

PX4_FOLDER = "px4"  # the run folder's sub-folder of PX4's working directories (its ULogs among them)


def px4_config(config: Config, instance: int) -> Config:
    """`config` for a drone flown by PX4 instance `instance`: the daemon on PX4's offboard link, reading
    PX4's events with the build's catalogue, and the radio map (if on) hearing PX4's ground-station
    link, which PX4 sends to 14550."""
    from dynqos.sim.vehicle.px4_sitl import Px4Ports, event_catalogue, px4_folder

    ports = Px4Ports(instance)
    events = event_catalogue(px4_folder(config.px4.dir))
    onboard = replace(
        config.onboard,
        mavlink_url=f"udpin:127.0.0.1:{ports.offboard_remote}",
        fc_system_id=ports.system_id,
        px4_events=str(events) if events else config.onboard.px4_events,
    )
    config = replace(config, onboard=onboard)
    if config.cell.radio.enabled:
        radio = replace(config.cell.radio, position_port=ports.gcs_remote)
        config = replace(config, cell=replace(config.cell, radio=radio))
    return config


def px4_instance(scenario: Scenario) -> int | None:
    """A free PX4 instance number for the scenario's drone (None: it flies dynqos's vehicle)."""
    if scenario.vehicle != "px4":
        return None
    from dynqos.sim.vehicle.px4_sitl import free_instances

    return free_instances(1)[0]


def start_vehicle(procs: Processes, folder: Path, instance: int | None, name: str = "vehicle") -> None:
    """The drone's vehicle: PX4 instance `instance` with its working directory in the run folder, or
    (None) dynqos's simulated vehicle."""
    if instance is None:
        procs.start(name, ["sim", "vehicle", "--duration", "3600"])
        return
    workdir = folder / PX4_FOLDER / f"i{instance}"
    procs.start(name, ["sim", "px4", "--instance", str(instance), "--workdir", str(workdir)], timeout_s=60)


def with_px4_flight(summary: dict[str, Any], workdir: Path, scenario: Scenario) -> None:
    """`summary` with what PX4 did (its ULog, dynqos/reports/px4_log.py); a flight PX4 did not fly in
    offboard mode throughout, or one in which PX4's failsafe fired, is not ok (docs/px4.md)."""
    from dynqos.reports.px4_log import px4_report

    report = px4_report(workdir, scenario.duration_s)
    summary["px4"] = report
    if not summary["ok"]:
        return
    if "error" in report:
        summary["ok"], summary["failure"] = False, f"PX4's ULog: {report['error']}"
    elif not report["offboard_whole_flight"]:
        summary["ok"], summary["failure"] = False, "PX4 did not fly the whole flight in OFFBOARD"
    elif report["failsafes"]:
        summary["ok"], summary["failure"] = False, f"PX4's failsafe fired: {report['failsafes'][0]}"
