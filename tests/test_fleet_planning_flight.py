"""A fleet's mission flown by `dynqos edge fleet-planner`, blind and planned, through the emulated cell's
radio map and operator: the shipped fleet-blind and fleet-planned scenarios cut to two drones and two
inspections, one of them over the small coverage hole, one a high-risk inspection by a pillar. Real
processes on 127.0.0.1 (docs/planning.md).

Blind, the drone that inspects the hole's site flies into it at 1.5 m: the cell carries nothing of its
uplink, its own daemon logs the hole's readings, the watchdog hands it to its fallback, which holds it
there (its downlink stalls with its uplink, as TCP's would). Planned, the prediction puts that
inspection at 5 m, above the hole, the other one is booked, and nothing falls back."""

from __future__ import annotations

import csv
import json
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import Scenario, builtin_scenario

TASKS = ("hole-site", "pillar-sw")


def _scenario(mode: str) -> Scenario:
    base = builtin_scenario(f"fleet-{mode}")
    plan = dict(base.config["fleet_plan"])
    plan["tasks"] = [t for t in plan["tasks"] if t["id"] in TASKS]
    # uav1 (-14, -10) is nearer the hole's site, uav2 (-14, 10) takes the pillar's: 40 s holds either plan
    return replace(base, drones=base.drones[:2], duration_s=40, config={**base.config, "fleet_plan": plan})


def _fly(tmp_path: Path, mode: str) -> tuple[dict[str, Any], Path]:
    scenario = _scenario(mode)
    summary = run_scenario(scenario, tmp_path, progress=False)
    return summary, tmp_path / scenario.run_id


def _sinr_min(folder: Path, uav: str) -> float:
    with (folder / "radio.csv").open(newline="") as f:
        return min(float(row["sinr_db"]) for row in csv.DictReader(f) if row["uav"] == uav)


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(300)
def test_blind_the_drone_at_the_holes_site_falls_back_and_holds_and_says_so(tmp_path: Path) -> None:
    summary, folder = _fly(tmp_path, "blind")
    mission = summary["mission"]
    assert mission["planned_with"] == "blind ([fleet_plan] mode)"
    rows = {r["task"]: r for r in mission["task_rows"]}
    assert rows["hole-site"]["drone"] == "uav1", rows
    assert rows["hole-site"]["completed"], rows  # it got there, and stayed: the fallback held it
    assert rows["hole-site"]["camera_kb"] == 0.0, rows  # nothing of its camera came up from the hole
    assert mission["fallback_s_by_drone"]["uav1"] > 5.0, mission
    assert mission["fallback_s_by_drone"]["uav2"] < 2.0, mission
    assert _sinr_min(folder, "uav1") <= -20  # the cell placed it in the hole
    # its own daemon says so: the modem's readings and the fallback in its last health line
    last = [
        line for line in (folder / "logs" / "onboard-uav1.log").read_text().splitlines() if "state=" in line
    ][-1]
    assert "control=fallback" in last, last
    sinr = re.search(r"sinr_db=(-?[\d.]+)", last)
    assert sinr is not None, last
    assert float(sinr.group(1)) <= -20, last
    assert json.loads((folder / "plan.json").read_text())["bookings"] == []
    assert summary["checks"]["nothing_left_booked"]
    assert (folder / "routes.png").stat().st_size > 10_000


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(300)
def test_planned_the_hole_is_inspected_from_above_the_pillar_is_booked_and_nothing_falls_back(
    tmp_path: Path,
) -> None:
    summary, folder = _fly(tmp_path, "planned")
    assert summary["ok"], summary["failure"]
    mission = summary["mission"]
    assert mission["planned_with"] == "prediction", mission
    assert mission["tasks_completed"] == 2, mission["task_rows"]
    plan = json.loads((folder / "plan.json").read_text())
    heights = {leg["task"]: leg["path_m"][0][2] for legs in plan["legs"].values() for leg in legs
               if leg["kind"] == "task"}  # fmt: skip
    assert heights == {"hole-site": 5.0, "pillar-sw": 1.5}, heights
    assert [(b["task"], b["status"]) for b in plan["bookings"]] == [("pillar-sw", "SCHEDULED")]
    assert plan["released"] == [plan["bookings"][0]["booking_id"]]
    assert summary["checks"]["nothing_left_booked"]
    assert mission["fallback_s"] < 2.0, mission
    rows = {r["task"]: r for r in mission["task_rows"]}
    assert rows["hole-site"]["camera_kb"] > 100, rows  # its camera came up from above the hole
    assert _sinr_min(folder, rows["hole-site"]["drone"]) > 0  # it never met the hole
