"""What became of a fleet's planned mission (docs/planning.md): the rows that compare `fleet-blind`
with `fleet-planned`, from the fleet planner's plan.json and what the flight recorded.

- **tasks completed**: a task counts when the vehicle (the simulator's own position, as the cell hears
  it on the ground-station port, so a drone whose uplink is silent in a hole is still seen) stays
  within `NEAR_M` of the task (its point, or its route) for `DONE_SHARE` of the task's window;
- **mission time**: from the plan's start to the last task's arrival at its site plus its time there;
- **time in fallback**: during the mission, from each status's control source and the moment it last
  changed (statuses lost in a hole do not hide the fallback they report afterwards), and wherever no
  state of the drone reached the edge for longer than the watchdog (the MPC answers states: without
  them no command goes out, and the drone's watchdog hands it to its fallback; a drone that stays in a
  hole never reports it);
- **camera bytes per inspection**: the bytes the cell delivered on the drone's two bearers during its
  inspection windows (the camera's, plus its states and statuses, some 10 kB/s, at the cell's scale);
- **priority-seconds booked vs used**: the booked windows' length, and the seconds of them in which the
  booked drone's supervisor had it on its priority flow.
"""

from __future__ import annotations

import csv
import itertools
import math
from pathlib import Path
from typing import Any

from dynqos.common.clock import NS_PER_S
from dynqos.common.modes import ControlSource
from dynqos.plan.recording import Recording
from dynqos.reports.figures import figure, mean_of
from dynqos.reports.outcomes import time_in_states

NEAR_M = 1.0
DONE_SHARE = 0.8
Track = list[tuple[int, float, float, float]]  # (monotonic ns, x, y, height)


def mission_figures(
    folder: Path, plan: dict[str, Any], rec: Recording, recs: dict[str, Recording], watchdog_s: float
) -> dict[str, Any]:
    start = int(plan["start_monotonic_ns"])
    tracks = vehicle_tracks(folder / "radio.csv", rec) or _state_tracks(recs)
    tasks = {t["id"]: t for t in plan["tasks"]}
    rows, arrivals = [], []
    inspect_bytes: list[float] = []
    for uav, legs in plan["legs"].items():
        for leg in legs:
            if leg["kind"] != "task":
                continue
            task = tasks[leg["task"]]
            lo, hi = start + round(leg["start_s"] * NS_PER_S), start + round(leg["end_s"] * NS_PER_S)
            near, arrived = _near(tracks.get(uav, []), leg["path_m"], lo, hi)
            row = {
                "task": task["id"],
                "kind": task["kind"],
                "drone": uav,
                "risk": task["risk"],
                "start_s": round(leg["start_s"], 2),
                "end_s": round(leg["end_s"], 2),
                "near_share": None if near is None else round(near, 3),
                "completed": near is not None and near >= DONE_SHARE,
            }
            if arrived is not None:
                arrivals.append((arrived - start) / NS_PER_S + (leg["end_s"] - leg["start_s"]))
            if task["kind"] == "inspect":
                delivered = _delivered(rec, uav, lo, hi)
                row["camera_kb"] = None if delivered is None else round(delivered / 1e3, 1)
                if delivered is not None:
                    inspect_bytes.append(delivered)
            rows.append(row)
    end = start + round(float(plan["mission_s"]) * NS_PER_S)
    fallback = {
        uav: round(fallback_s(recs[uav], start, end, round(watchdog_s * NS_PER_S)), 2)
        for uav in plan["legs"]
        if uav in recs
    }
    booked, used = _priority(plan, recs, start)
    return {
        "planned_with": plan["planned_with"],
        "mission_s_planned": round(float(plan["mission_s"]), 2),
        "mission_s": round(max(arrivals), 2) if arrivals else None,
        "tasks": len(rows),
        "tasks_completed": sum(r["completed"] for r in rows),
        "fallback_s": round(sum(fallback.values()), 2),
        "fallback_s_by_drone": fallback,
        "camera_kb_per_inspection": (
            round(sum(inspect_bytes) / len(inspect_bytes) / 1e3, 1) if inspect_bytes else None
        ),
        "priority_s_booked": round(booked, 2),
        "priority_s_used": round(used, 2),
        "bookings": sum(1 for b in plan["bookings"] if b["booking_id"]),
        "bookings_refused": sum(1 for b in plan["bookings"] if not b["booking_id"]),
        "released": len(plan["released"]),
        "release_failed": len(plan["release_failed"]),
        "task_rows": rows,
    }


def vehicle_tracks(path: Path, rec: Recording) -> dict[str, Track]:
    """Each vehicle's positions from the cell's radio.csv, on the recorder's monotonic clock (the cell's
    time zero from its counters, which carry both its own time and the moment they were read)."""
    if not path.exists() or not rec.cell:
        return {}
    offsets = sorted(c["now_ns"] - round(float(c["t_s"]) * NS_PER_S) for c in rec.cell)
    zero = offsets[len(offsets) // 2]
    out: dict[str, Track] = {}
    with path.open(newline="") as f:
        for row in csv.DictReader(f):
            t = zero + round(float(row["t_s"]) * NS_PER_S)
            point = (t, float(row["x_m"]), float(row["y_m"]), -float(row["z_m"]))
            out.setdefault(row["uav"], []).append(point)
    return out


def _state_tracks(recs: dict[str, Recording]) -> dict[str, Track]:
    return {uav: [(s.stamp_ns, *s.pos_m[:2], -s.pos_m[2]) for _, s in r.states] for uav, r in recs.items()}


def _distance(p: tuple[float, float, float], path: list[list[float]]) -> float:
    """From a point to a polyline of (x, y, height) (a single point is a polyline of one)."""
    if len(path) == 1:
        return math.dist(p, path[0])
    best = math.inf
    for a, b in itertools.pairwise(path):
        ab = [v - u for u, v in zip(a, b, strict=True)]
        length2 = sum(c * c for c in ab) or 1e-12
        f = max(0.0, min(1.0, sum((p[i] - a[i]) * ab[i] for i in range(3)) / length2))
        best = min(best, math.dist(p, [a[i] + f * ab[i] for i in range(3)]))
    return best


def _near(track: Track, path: list[list[float]], lo: int, hi: int) -> tuple[float | None, int | None]:
    """The share of the window's samples within NEAR_M of the task, and when the drone first got there
    (from 2 s before the window: a drone may arrive early)."""
    early = lo - 2 * NS_PER_S
    inside = [(t, _distance((x, y, h), path) <= NEAR_M) for t, x, y, h in track if early <= t <= hi]
    window = [ok for t, ok in inside if t >= lo]
    arrived = next((t for t, ok in inside if ok), None)
    return (sum(window) / len(window) if window else None), arrived


def _delivered(rec: Recording, uav: str, lo: int, hi: int) -> float | None:
    """Bytes the cell delivered on the drone's bearers between lo and hi (its counters, interpolated)."""
    mine = (f"{uav}-default", f"{uav}-priority")
    samples = [
        (c["now_ns"], sum(b["delivered_bytes"] for name, b in c["bearers"].items() if name in mine))
        for c in rec.cell
    ]
    if len(samples) < 2 or samples[0][0] > lo or samples[-1][0] < hi:
        return None

    def at(t: int) -> float:
        for (t0, v0), (t1, v1) in itertools.pairwise(samples):
            if t0 <= t <= t1:
                return float(v0 + (v1 - v0) * (t - t0) / max(1, t1 - t0))
        return float(samples[-1][1])

    return at(hi) - at(lo)


def fallback_s(rec: Recording, lo: int, hi: int, watchdog_ns: int) -> float:
    """Seconds in [lo, hi) flown by the fallback: where the statuses say so (from when each says its
    control source began) or where no state reached the edge for longer than the watchdog."""
    statuses = sorted(rec.status, key=lambda s: s.stamp_ns)
    changes = sorted(
        {
            (s.control_changed_ns, str(getattr(s.control_source, "value", s.control_source)))
            for s in statuses
            if s.control_changed_ns
        }
    )
    spans = [
        (t, t_next)
        for (t, source), (t_next, _) in itertools.pairwise([*changes, (hi, "")])
        if source == ControlSource.FALLBACK.value
    ]
    arrivals = sorted(state.stamp_ns + round(latency_ms * 1e6) for latency_ms, state in rec.states)
    for a, b in itertools.pairwise([lo, *(t for t in arrivals if lo <= t <= hi), hi]):
        if b - a > watchdog_ns:
            spans.append((a + watchdog_ns, b))
    return _union_s(spans, lo, hi)


def _union_s(spans: list[tuple[int, int]], lo: int, hi: int) -> float:
    total, reach = 0, lo
    for a, b in sorted(spans):
        a, b = max(a, reach), min(b, hi)
        if b > a:
            total += b - a
            reach = b
    return total / NS_PER_S


def _priority(plan: dict[str, Any], recs: dict[str, Recording], start: int) -> tuple[float, float]:
    booked = used = 0.0
    for b in plan["bookings"]:
        if not b["booking_id"] or b["drone"] not in recs:
            continue
        lo = start + round(b["start_s"] * NS_PER_S)
        hi = lo + round(b["duration_s"] * NS_PER_S)
        booked += (hi - lo) / NS_PER_S
        statuses = sorted(recs[b["drone"]].status, key=lambda s: s.stamp_ns)
        used += time_in_states(statuses, field="flow", within=(lo, hi)).get("priority", 0.0)
    return booked, used


# ---- report.md ------------------------------------------------------------------------------------------

ROWS = (
    ("tasks completed", "mission.tasks_completed", 1),
    ("mission time (s)", "mission.mission_s", 1),
    ("time in fallback, all drones (s)", "mission.fallback_s", 1),
    ("camera kB delivered per inspection", "mission.camera_kb_per_inspection", 0),
    ("priority-seconds booked", "mission.priority_s_booked", 1),
    ("priority-seconds of them used", "mission.priority_s_used", 1),
)


def mission_comparison(fleets: list[dict[str, Any]]) -> list[str]:
    """The planned missions side by side (docs/planning.md): each measure per scenario, as mean [95%
    interval] over repeated runs, and each scenario's mean against the first one's."""
    planned = [s for s in fleets if "mission" in (s["runs"][0] if "aggregate" in s else s)]
    if not planned:
        return []
    firsts = [s["runs"][0] if "aggregate" in s else s for s in planned]
    lines = [
        "### Missions planned by the network, and flown blind",
        "",
        "| measure | " + " | ".join(s["scenario"] for s in firsts) + " |",
        "|---|" + "---|" * len(planned),
        "| planned with | " + " | ".join(str(s["mission"]["planned_with"]) for s in firsts) + " |",
        "| tasks | " + " | ".join(str(s["mission"]["tasks"]) for s in firsts) + " |",
    ]
    for label, path, digits in ROWS:
        base = mean_of(planned[0], path)
        cells = []
        for s in planned:
            text = figure(s, path, digits)
            mean = mean_of(s, path)
            if s is not planned[0] and base and mean is not None:
                text += f" ({(mean / base - 1) * 100:+.0f}%)"
            cells.append(text)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    runs = ", ".join(str(len(s["runs"]) if "aggregate" in s else 1) for s in planned)
    lines += ["", f"Runs (seeds) per scenario: {runs}; in brackets: against the first.", ""]
    return lines
