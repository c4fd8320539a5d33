"""What a planned mission's report measures (dynqos/reports/mission.py), pure: tasks done from the
vehicle's own track, time in fallback from the statuses and from the silences no status reports, the
camera bytes the cell delivered in each inspection, priority booked against used, and the comparison
table of report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from dynqos.common.messages import State, SupervisorStatus
from dynqos.plan.recording import Recording
from dynqos.reports.aggregate import aggregate
from dynqos.reports.mission import fallback_s, mission_comparison, mission_figures
from tests.statuses import status as quiet

S = 1_000_000_000
START = 100 * S  # the plan's start, on the recorder's clock
WATCHDOG = S // 10


def status(
    t_s: float, source: str = "edge", changed_s: float = 0.0, flow: str = "default"
) -> SupervisorStatus:
    return quiet(
        stamp_ns=START + round(t_s * S),
        flow=flow,
        control_source=source,
        control_changed_ns=START + round(changed_s * S),
    )


def states(*seconds: float) -> list[tuple[float, State]]:
    """States that reached the edge 10 ms after their stamps."""
    return [
        (10.0, State(uav="uav1", seq=i, stamp_ns=START + round(t * S) - 10_000_000, pos_m=(0.0, 0.0, -1.5),
                     vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0)))
        for i, t in enumerate(seconds)
    ]  # fmt: skip


def test_fallback_counts_what_the_statuses_say_and_every_silence_past_the_watchdog() -> None:
    rec = Recording()
    # the edge flew it until 2 s, the fallback from 2 s to 3 s (said by a status at 3.5 s), the edge again
    rec.status = [status(1.0), status(3.5, "edge", changed_s=3.0), status(2.5, "fallback", changed_s=2.0)]
    rec.states = states(*[k / 10 for k in range(0, 61)], 9.0)  # every 0.1 s to 6 s, then one at 9 s
    # the statuses' second; the silences after 6 s (to 9 s) and after 9 s (to 10 s), each less the watchdog
    assert fallback_s(rec, START, START + 10 * S, WATCHDOG) == pytest.approx(1.0 + 2.9 + 0.9)
    assert fallback_s(rec, START + 2 * S + S // 2, START + 4 * S, WATCHDOG) == pytest.approx(0.5)


def _folder(tmp_path: Path) -> Path:
    """radio.csv as the cell writes it: its own time from its start, which is START - 5 s here."""
    rows = ["t_s,uav,x_m,y_m,z_m,rsrp_dbm,sinr_db,cqi,rate_factor"]
    for k in range(0, 201):  # uav1 reaches (4, 0) at 1.5 m at 4 s and stays; uav2 never leaves (0, 9)
        t = k / 10
        rows.append(f"{t + 5:.3f},uav1,{min(t, 4.0):.2f},0.00,-1.50,-78,15,10,1.0")
        rows.append(f"{t + 5:.3f},uav2,0.00,9.00,-1.50,-78,15,10,1.0")
    (tmp_path / "radio.csv").write_text("\n".join(rows) + "\n")
    return tmp_path


def _plan() -> dict[str, Any]:
    task = {"kind": "inspect", "duration_s": 5.0}

    def leg(kind: str, start: float, end: float, path: list[list[float]], task: str) -> dict[str, Any]:
        return {"kind": kind, "start_s": start, "end_s": end, "path_m": path, "task": task}

    return {
        "planned_with": "prediction", "mission_s": 10.0, "start_monotonic_ns": START,
        "tasks": [{"id": "a", "points_m": [[4.0, 0.0]], "risk": "high", **task},
                  {"id": "b", "points_m": [[0.0, 5.0]], "risk": "low", **task}],
        "legs": {"uav1": [leg("fly", 0.0, 4.0, [[0, 0, 1.5], [4, 0, 1.5]], "a"),
                          leg("task", 4.0, 9.0, [[4.0, 0.0, 1.5]], "a")],
                 "uav2": [leg("task", 0.0, 5.0, [[0.0, 5.0, 1.5]], "b")]},
        "bookings": [{"drone": "uav1", "task": "a", "start_s": 4.0, "duration_s": 5.0, "booking_id": "x"},
                     {"drone": "uav2", "task": "b", "start_s": 0.0, "duration_s": 5.0, "booking_id": ""}],
        "released": ["x"], "release_failed": [],
    }  # fmt: skip


def test_a_mission_is_measured_from_the_track_the_cell_and_the_statuses(tmp_path: Path) -> None:
    rec = Recording()
    # the cell's counters every second: its own time and the recorder's; uav1 delivers 1000 bytes a second
    rec.cell = [
        {"t_s": t + 5.0, "now_ns": START + t * S,
         "bearers": {"uav1-default": {"delivered_bytes": 1000 * t}, "uav2-priority": {"delivered_bytes": 0}}}
        for t in range(-1, 12)
    ]  # fmt: skip
    one, two = Recording(), Recording()
    one.states = states(*[k / 10 for k in range(0, 111)])
    two.states = states(*[k / 10 for k in range(0, 111)])
    one.status = [status(t, flow="priority" if 5.0 <= t < 7.0 else "default") for t in range(0, 11)]
    out = mission_figures(_folder(tmp_path), _plan(), rec, {"uav1": one, "uav2": two}, 0.15)
    assert out["tasks"] == 2
    assert out["tasks_completed"] == 1  # uav1 at its site; uav2 never went to (0, 5)
    assert [(r["task"], r["completed"]) for r in out["task_rows"]] == [("a", True), ("b", False)]
    assert out["mission_s"] == pytest.approx(3.0 + 5.0, abs=0.15)  # within 1 m at 3 s, then 5 s on station
    assert out["camera_kb_per_inspection"] == pytest.approx(
        (5.0 + 0.0) / 2
    )  # 5000 bytes in a's 5 s, 0 in b's
    assert out["fallback_s"] == 0.0
    assert (out["priority_s_booked"], out["priority_s_used"]) == (5.0, pytest.approx(2.0))
    assert (out["bookings"], out["bookings_refused"], out["released"]) == (1, 1, 1)


def test_the_report_sets_the_scenarios_side_by_side_with_the_planned_against_the_blind() -> None:
    def run(name: str, fallback: float, kb: float) -> dict[str, Any]:
        mission = {"planned_with": name, "tasks": 8, "tasks_completed": 8, "mission_s": 50.0,
                   "fallback_s": fallback, "camera_kb_per_inspection": kb, "priority_s_booked": 0.0,
                   "priority_s_used": 0.0}  # fmt: skip
        return {"scenario": name, "fleet": True, "mission": mission}

    blind = [run("fleet-blind", 20.0, 1000.0), run("fleet-blind", 30.0, 1200.0)]
    planned = run("fleet-planned", 5.0, 1650.0)
    repeated = {"scenario": "fleet-blind", "runs": blind, "aggregate": aggregate(blind)}
    lines = mission_comparison([repeated, planned])
    text = "\n".join(lines)
    assert "| measure | fleet-blind | fleet-planned |" in text
    fallback = next(line for line in lines if line.startswith("| time in fallback"))
    assert fallback.startswith("| time in fallback, all drones (s) | 25.0 [")  # mean [95% interval] of two
    assert fallback.endswith("| 5.0 (-80%) |")
    assert "| 1650 (+50%) |" in text
    assert mission_comparison([{"scenario": "fleet-arbiter", "fleet": True}]) == []
