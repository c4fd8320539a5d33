"""The run folder of a flight once every process stopped: the summary of one drone (dynqos/reports/
summary.py) or of a fleet (dynqos/reports/fleet.py), with what only the runner can add: each drone's
paths over two sites, the QoD sessions each site's operator was left with, what PX4 did, and what
became of a planned mission."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from dynqos.common.config import Config
from dynqos.experiment.sites import operators_qod
from dynqos.experiment.vehicles import contacts, track, with_px4_flight, world_of
from dynqos.plan.faults import SITE_FAULTS
from dynqos.plan.flight import SHARED, FlightPlan, px4_workdir
from dynqos.plan.recording import FlightRecords
from dynqos.plan.scenario import Scenario
from dynqos.reports.fleet import summarise_fleet, write_fleet
from dynqos.reports.mission import mission_figures, vehicle_tracks
from dynqos.reports.multipath import fault_spans, path_figures
from dynqos.reports.routes import plot_routes
from dynqos.reports.summary import summarise, write_scenario


def write_report(
    scenario: Scenario,
    plan: FlightPlan,
    folder: Path,
    configs: dict[str, Config],
    records: FlightRecords,
    px4: list[int] | None,
    *,
    ok: bool,
    failure: str,
) -> dict[str, Any]:
    """Write the run folder and return its summary. A fleet's summary holds each drone's figures under
    `drones`; one drone's are the summary's own."""
    rec, drones = records.flight, records.drones
    onboard = zip(plan.drones, plan.onboard, strict=True)
    logs = {uav: _read(folder / "logs" / f"{item.name}.log") for uav, item in onboard}
    if scenario.fleet:
        summary = summarise_fleet(scenario, rec, drones, records.decisions, logs, ok=ok, failure=failure)
        each_drone = summary["drones"]
    else:
        summary = summarise(scenario, rec, logs[plan.drones[0]], ok=ok, failure=failure)
        each_drone = {plan.drones[0]: summary}
    summary["vehicle"] = scenario.vehicle
    if not scenario.fleet and (scenario.sites == 2 or any(f.kind in SITE_FAULTS for f in scenario.faults)):
        summary["multipath"] = path_figures(rec.status, rec.t0_ns, *fault_spans(rec.faults))
    if scenario.sites == 2 and scenario.qos_backend == "camara":  # sessions at each site's operator
        summary.setdefault("qos_network", {})["operators"] = operators_qod(folder)
    for uav, key, instance in zip(plan.drones, plan.drone_configs(), px4 or [], strict=False):
        with_px4_flight(summary, px4_workdir(folder, instance), scenario, uav if scenario.fleet else None)
        each_drone[uav]["px4"]["contacts"] = contacts(world_of(configs[key]), track(drones[uav]))
    if (folder / "plan.json").exists():  # a planned mission (docs/planning.md): what became of it
        mission = json.loads((folder / "plan.json").read_text())
        shared = configs[SHARED]
        summary["mission"] = mission_figures(folder, mission, rec, drones, shared.supervisor.watchdog_s)
        plot_routes(folder, mission, shared, vehicle_tracks(folder / "radio.csv", rec))
        summary["checks"]["nothing_left_booked"] = not mission["release_failed"]
    if scenario.fleet:
        write_fleet(folder, scenario, rec, drones, records.decisions, summary)
    else:
        write_scenario(folder, scenario, rec, summary)
    return summary


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""
