"""report.md over every scenario of a run, beside the paper's Table II: one run's figures as measured,
a repeated scenario's as mean and 95% interval over its runs (dynqos/reports/aggregate.py), and, when the
paper's profile flew, what the paper's parameters did at the paper's baseline."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from dynqos.plan.scenario import run_id
from dynqos.reports import machine
from dynqos.reports.aggregate import interval
from dynqos.reports.figures import figure, fmt, interval_text, lookup, mean_of
from dynqos.reports.fleet import fleet_comparison, fleet_section
from dynqos.reports.measures import rmse
from dynqos.reports.mission import mission_comparison
from dynqos.reports.multipath import multipath_lines
from dynqos.reports.tasks import task_lines
from dynqos.reports.uplink import traced_lines

PAPER_TABLE_II = {
    "No QoS - No BG": {"uav_tx": 47, "uav_rx": 47, "rtt": "27.3", "bg_tx": None, "bg_rx": None},
    "No QoS - BG": {"uav_tx": 47, "uav_rx": 40, "rtt": "rises", "bg_tx": 80, "bg_rx": 40},
    "Priority QoS - BG": {"uav_tx": 47, "uav_rx": 47, "rtt": "28.1", "bg_tx": 80, "bg_rx": 32.5},
}
SCENARIO_ROW = {
    "baseline": "No QoS - No BG",
    "bg-noqos": "No QoS - BG",
    "bg-staticqos": "Priority QoS - BG",
    "bg-dynqos": "Priority QoS - BG",
    "bg-dynqos-hover": "Priority QoS - BG",
}


def _run_id(summary: dict[str, Any]) -> str:
    return run_id(summary["scenario"], summary.get("profile", "dynqos"))


def _loaded(summary: dict[str, Any]) -> bool:
    runs = summary.get("runs", [summary])
    return any(run.get("bg_start_s") is not None for run in runs)


def write_report(out: Path, summaries: list[dict[str, Any]]) -> None:
    fleets = [s for s in summaries if s.get("fleet")]
    summaries = [s for s in summaries if not s.get("fleet")]
    repeated = any("aggregate" in s for s in summaries)
    lines = [
        "# dynqos demo report",
        "",
        "The paper's scenarios, run on this machine through the emulated cell (see docs/cell.md). "
        "Rates are at full scale; the run itself used 1/scale of every rate.",
        *(
            ["", "Repeated scenarios show each figure as mean [95% interval] over their runs (seeds)."]
            if repeated
            else []
        ),
    ]
    if summaries:
        lines += _single_scenarios(out, summaries, repeated)
    if fleets:
        lines += ["", "## Fleets", "", "Several drones in one cell (docs/fleet.md). Rates at full scale.", ""]
        lines += fleet_comparison(fleets)
        lines += mission_comparison(fleets)
        for s in fleets:
            lines += fleet_section(s)
    (out / "report.md").write_text("\n".join(lines) + "\n")


def _single_scenarios(out: Path, summaries: list[dict[str, Any]], repeated: bool) -> list[str]:
    lines = [
        "",
        "## Beside the paper's Table II",
        "",
        "UAV: what the drone's application offered (every uplink message handed to zenoh: camera, state, "
        "status), what the cell "
        "admitted into the drone's bearers and what it delivered. BG: the load configured, what the "
        "background got. Over the loaded span (after settling when there is no load).",
        "",
        "| scenario | profile | runs | paper row | UAV offered / admitted / delivered (Mbit/s) "
        "| paper UAV Tx / Rx | RTT mean baseline / loaded (ms) | paper RTT (ms) "
        "| BG configured / delivered (Mbit/s) | paper BG Tx / Rx | ok |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_table_row(s) for s in summaries]
    lines += _paper_profile_lines(summaries)
    lines += traced_lines(summaries)
    lines += multipath_lines(summaries)
    if repeated:
        _spread_plot(out, summaries)
        lines += ["", "![RTT over repeated runs](spread.png)"]
    lines += ["", "## Scenarios", ""]
    baseline = next((s for s in summaries if _run_id(s) == "baseline" and "aggregate" not in s), None)
    for s in summaries:
        lines += _repeated_section(s) if "aggregate" in s else _single_section(out, s, baseline)
    return lines


def _table_row(s: dict[str, Any]) -> str:
    row = SCENARIO_ROW.get(s["scenario"], "-")
    paper = PAPER_TABLE_II.get(row, {})
    bg = fmt(s.get("bg_mbps"), 0)
    cells = [
        s["scenario"],
        s.get("profile", "dynqos"),
        str(len(s.get("runs", [s]))),
        row,
        f"{figure(s, 'uav_offered_mbps')} / {figure(s, 'uav_admitted_mbps')} / "
        f"{figure(s, 'uav_delivered_mbps')}",
        f"{paper.get('uav_tx', '-')} / {paper.get('uav_rx', '-')}",
        f"{figure(s, 'rtt_ms.baseline.mean')} / {figure(s, 'rtt_ms.loaded.mean')}",
        str(paper.get("rtt", "-")),
        f"{bg if _loaded(s) else '-'} / {figure(s, 'bg_delivered_mbps')}",
        f"{paper.get('bg_tx') or '-'} / {paper.get('bg_rx') or '-'}",
        str(s["ok"]),
    ]
    return "| " + " | ".join(cells) + " |"


def _paper_profile_lines(summaries: list[dict[str, Any]]) -> list[str]:
    """In plain words, what the paper's parameters do at the paper's own unloaded RTT."""
    paper = [s for s in summaries if s.get("profile") == "paper"]
    if not paper:
        return []
    lines = ["", "## The paper's parameters at the paper's baseline", ""]
    for s in paper:
        hl = mean_of(s, "hl_fraction_baseline")
        share = "-" if hl is None else f"{100 * hl:.0f}%"
        lines.append(
            f"- {s['scenario']}: unloaded C&C RTT {figure(s, 'rtt_ms.baseline.mean')} ms against the "
            f"paper's rho2 = 27 ms; the supervisor read high latency in {share} of the unloaded flight's "
            f"statuses, with no load at all."
        )
    lines.append(
        "- With rho2 at the unloaded RTT, the C&C sigmoid sits near 0.5 or above before any load, and "
        "P_lat = 0.35 P_cam + 0.65 P_cc crosses th_lat = 0.5 on the RTT's own jitter: the paper's "
        "supervisor then moves to (or stays on) the priority flow for latency it should call low. dynqos's "
        'profile keeps the unloaded RTT well below rho2 (docs/demo.md, "Profiles").'
    )
    return lines


def _single_section(out: Path, s: dict[str, Any], baseline: dict[str, Any] | None) -> list[str]:
    rtt, cam, error_m = s["rtt_ms"], s["camera_latency_ms"], s["tracking_rmse_m"]
    run_id = _run_id(s)
    return [
        f"### {run_id}",
        "",
        s["description"],
        "",
        f"- RTT (ms): baseline mean {fmt(rtt['baseline']['mean'])}, p95 {fmt(rtt['baseline']['p95'])}; "
        f"loaded mean {fmt((rtt['loaded'] or {}).get('mean'))}, "
        f"p95 {fmt((rtt['loaded'] or {}).get('p95'))}, max {fmt((rtt['loaded'] or {}).get('max'))}",
        f"- camera latency (ms): baseline mean {fmt(cam['baseline']['mean'])}; loaded mean "
        f"{fmt((cam['loaded'] or {}).get('mean'))}",
        f"- tracking RMSE (m): baseline {fmt(error_m['baseline'], 3)}, loaded {fmt(error_m['loaded'], 3)}",
        *_same_wind_line(out, s, baseline),
        f"- first switch to the priority flow after the background started: "
        f"{fmt(s['first_qos_switch_after_bg_s'], 2)} s ({s['first_qos_switch_cause'] or 'none'}); "
        f"fallback entered: {s['fallback_entered']}; "
        f"largest setpoint gap: {fmt(s['setpoint_gap_max_ms'])} ms",
        *_takeoff_line(s),
        *_px4_lines(s),
        *_camera_line(s),
        *_qos_network_line(s),
        *_fault_lines(s),
        *task_lines(s),
        "- time in states (s): " + ", ".join(f"{k} {v:.1f}" for k, v in s["states_time_s"].items() if v > 0),
        f"- {machine.describe(s.get('machine'))}",
        f"- ok: {s['ok']} {s['failure']}",
        "",
        f"![{run_id}]({run_id}/overview.png)",
        "",
        f"![{run_id} supervisor]({run_id}/supervisor.png)",
        "",
    ]


def _qos_network_line(s: dict[str, Any]) -> list[str]:
    """What the network made of the drone's priority (docs/qos.md): grant and RTT after the decision,
    and the QoD sessions (or NEF subscriptions) the emulated operator saw."""
    q = s.get("qos_network")
    if not q or s.get("qos") == "default":
        return []
    line = (
        f"- network QoS ({q['backend']}): from the decision to the priority flow, grant AVAILABLE after "
        f"{fmt(q['decision_to_available_s'], 2)} s, RTT back within 1.2x after "
        f"{fmt(q['decision_to_rtt_back_s'], 2)} s; grant at the end: {q['grant_at_end']}"
    )
    sessions = q.get("sessions")
    if sessions:
        line += (
            f"; QoD sessions created {sessions['created']}, extended {sessions['extended']}, "
            f"deleted {sessions['deleted']}, refused {sessions['refused']}, "
            f"left open {sessions['open_at_end']}"
        )
    subs = q.get("subscriptions")
    if subs:
        line += (
            f"; NEF subscriptions created {subs['created']}, deleted {subs['deleted']}, "
            f"refused {subs['refused']}, ended by the network {subs['terminated']}, "
            f"left open {subs['open_at_end']}"
        )
        line += f", QoS monitoring reports {subs['reports']}" if subs.get("reports") else ""
    return [line]


def _fault_lines(s: dict[str, Any]) -> list[str]:
    """Each injected fault or network change: what the drone saw and did while it lasted."""
    lines = []
    for f in s.get("faults", []):
        rtt = f.get("rtt_ms_during") or {}
        states = ", ".join(f"{k} {v:.1f}" for k, v in (f.get("states_s_during") or {}).items())
        slowed = f.get("camera_slowed_after_s")
        worst = f.get("max_tracking_error_m")
        lines.append(
            f"- {f['kind']} at {f['at_s']:g} s for {f['duration_s']:g} s: RTT while it lasted mean "
            f"{fmt(rtt.get('mean'))}, p95 {fmt(rtt.get('p95'))} ms; states (s) {states or '-'}; camera "
            + ("never slowed" if slowed is None else f"slowed {slowed:.2f} s after it began")
            + f"; fallback {f['fallback']}"
            + (" (already at its start)" if f.get("fallback_at_start") else "")
            + ("" if worst is None else f"; worst tracking error {worst:.2f} m")
        )
    return lines


def _repeated_fault_lines(s: dict[str, Any]) -> list[str]:
    """`_fault_lines` over repeated runs: each figure as mean [95% interval], each flag as k of N runs.
    A state a run never entered while the fault lasted counts as 0 s there."""
    runs = s["runs"]
    lines = []
    for index, f in enumerate(runs[0].get("faults", [])):
        p = f"faults.{index}."
        during = [run["faults"][index].get("states_s_during") or {} for run in runs]
        states = ", ".join(
            f"{k} {interval_text(interval([float(d.get(k, 0.0)) for d in during]))}"
            for k in sorted({k for d in during for k in d})
        )
        slowed = sum(run["faults"][index].get("camera_slowed_after_s") is not None for run in runs)
        fallback = sum(bool(run["faults"][index].get("fallback")) for run in runs)
        lines.append(
            f"- {f['kind']} at {f['at_s']:g} s for {f['duration_s']:g} s: RTT while it lasted mean "
            f"{figure(s, p + 'rtt_ms_during.mean')}, p95 {figure(s, p + 'rtt_ms_during.p95')} ms; "
            f"states (s) {states or '-'}; camera slowed in {slowed} of {len(runs)} runs"
            + (f", {figure(s, p + 'camera_slowed_after_s', 2)} s after it began" if slowed else "")
            + f"; fallback in {fallback} of {len(runs)} runs"
        )
    return lines


def _repeated_section(s: dict[str, Any]) -> list[str]:
    run_id = _run_id(s)
    seeds = [run.get("seed") for run in s["runs"]]
    lines = [
        f"### {run_id} ({len(s['runs'])} runs, seeds {', '.join(map(str, seeds))})",
        "",
        s["description"],
        "",
        f"- RTT (ms): baseline mean {figure(s, 'rtt_ms.baseline.mean')}, "
        f"p95 {figure(s, 'rtt_ms.baseline.p95')}; loaded mean {figure(s, 'rtt_ms.loaded.mean')}, "
        f"p95 {figure(s, 'rtt_ms.loaded.p95')}",
        f"- tracking RMSE (m): baseline {figure(s, 'tracking_rmse_m.baseline', 3)}, "
        f"loaded {figure(s, 'tracking_rmse_m.loaded', 3)}",
        f"- first switch to the priority flow after the background started: "
        f"{figure(s, 'first_qos_switch_after_bg_s', 2)} s (causes: "
        f"{'; '.join(sorted({run['first_qos_switch_cause'] or 'none' for run in s['runs']}))})",
        f"- camera frames/s acknowledged before the load: {figure(s, 'camera_fps.baseline')}",
        f"- network QoS: grant AVAILABLE {figure(s, 'qos_network.decision_to_available_s', 2)} s and RTT "
        f"back within 1.2x {figure(s, 'qos_network.decision_to_rtt_back_s', 2)} s after the decision",
        *_repeated_fault_lines(s),
        *_repeated_px4_line(s),
        *[f"- seed {run.get('seed')}: {machine.describe(run.get('machine'))}" for run in s["runs"]],
        f"- ok: {s['ok']} {s['failure']}",
        "",
    ]
    for run in s["runs"]:
        seed = run.get("seed")
        lines.append(f"![{run_id} seed {seed}]({run_id}/seed{seed}/overview.png)")
    return [*lines, ""]


def _spread_plot(out: Path, summaries: list[dict[str, Any]]) -> None:
    """Each scenario's per-run RTT means (before and under the load) with their mean and 95% interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(summaries)), 4.0))
    for i, s in enumerate(summaries):
        for offset, path, colour in (
            (-0.15, "rtt_ms.baseline.mean", "tab:blue"),
            (0.15, "rtt_ms.loaded.mean", "tab:red"),
        ):
            values = [v for run in s.get("runs", [s]) if isinstance(v := lookup(run, path), (int, float))]
            if not values:
                continue
            ax.scatter([i + offset] * len(values), values, color=colour, alpha=0.5, s=14)
            agg = s.get("aggregate", {}).get(path)
            if agg is not None and agg["n"] >= 2:
                error = [[agg["mean"] - agg["ci95_low"]], [agg["ci95_high"] - agg["mean"]]]
                ax.errorbar([i + offset], [agg["mean"]], yerr=error, color=colour, capsize=4, fmt="_")
    ax.set_xticks(range(len(summaries)), [_run_id(s) for s in summaries], rotation=20)
    ax.set_ylabel("C&C RTT mean (ms): before (blue) and under (red) the load")
    if any(math.isfinite(v) and v > 0 for v in ax.get_ylim()):
        ax.set_yscale("log")
    fig.tight_layout()
    fig.savefig(out / "spread.png", dpi=100)
    plt.close(fig)


def _takeoff_line(s: dict[str, Any]) -> list[str]:
    """Hand-overs to the fallback before the flight's t=0 (during take-off): said apart from the flight."""
    before = (s.get("fallbacks") or {}).get("before_flight", 0)
    if not before:
        return []
    return [f"- take-off (before t=0, not counted above): {before} hand-over(s) to the fallback"]


def _px4_lines(s: dict[str, Any]) -> list[str]:
    """What PX4 itself did, from its ULog (dynqos/reports/px4_log.py)."""
    px4 = s.get("px4")
    if not px4:
        return []
    if "error" in px4:
        return [f"- PX4 (vehicle = px4): {px4['error']}"]
    modes = " -> ".join(f"{m['mode']} {m['duration_s']:.1f} s" for m in px4["modes"])
    failsafes = ", ".join(f"{f['mode']} at {f['t_s']:.1f} s" for f in px4["failsafes"]) or "none"
    touched = ", ".join(f"{c['with']} at {c['t_s']:.1f} s" for c in px4.get("contacts", [])) or "none"
    lines = [
        f"- PX4's own log ({px4['file']}): {modes}; OFFBOARD for the whole flight: "
        f"{px4['offboard_whole_flight']}; failsafes: {failsafes}; contacts with the world: {touched}"
    ]
    if px4["warnings"]:
        lines.append(
            "- PX4's warnings: " + "; ".join(f"{w['text']} ({w['t_s']:.1f} s)" for w in px4["warnings"])
        )
    return lines


def _repeated_px4_line(s: dict[str, Any]) -> list[str]:
    """Flown by PX4: in how many runs its own log shows OFFBOARD for the whole flight, and its failsafes."""
    flown = [run["px4"] for run in s["runs"] if run.get("px4")]
    if not flown:
        return []
    whole = sum(1 for p in flown if p.get("offboard_whole_flight"))
    failsafes = sum(len(p.get("failsafes", [])) for p in flown)
    return [
        f"- PX4's own logs: OFFBOARD for the whole flight in {whole} of {len(flown)} runs, "
        f"OFFBOARD {figure(s, 'px4.offboard_s')} s; failsafes: {failsafes}"
    ]


def _camera_line(s: dict[str, Any]) -> list[str]:
    fps = s["camera_fps"]
    line = (
        f"- camera: {fmt(fps['baseline'])} of {fmt(fps['configured'])} frames/s acknowledged before the load"
        f", {fmt(fps['loaded'])} under it"
    )
    if fps["baseline"] is not None and fps["baseline"] < 0.9 * fps["configured"]:
        line += (
            " **(the camera did not keep its rate: this machine offered less than the scenario asks, so "
            'the load on the drone\'s flow is understated; see docs/demo.md, "Scaling")**'
        )
    return [line]


def _same_wind_line(out: Path, s: dict[str, Any], baseline: dict[str, Any] | None) -> list[str]:
    """The baseline scenario flies the same mission in the same wind (same seed) with no load: over the
    same spans it shows how much of a loaded/baseline RMSE ratio is the gusts' and how much the load's."""
    start = s.get("bg_start_s")
    if start is None or baseline is None or baseline["mission"] != s["mission"]:
        return []
    if (baseline["seed"], baseline["scale"]) != (s["seed"], s["scale"]):
        return []
    errors = tracking_errors_csv(out / "baseline" / "states.csv")
    if errors is None:
        return []
    before = rmse([e for t, e in errors if s.get("settle_s", 0.0) <= t < start])
    after = rmse([e for t, e in errors if t >= start])
    if before is None or after is None:
        return []
    return [
        f"- the baseline scenario (the same wind, no load) over the same spans: {fmt(before, 3)} / "
        f"{fmt(after, 3)} m ({after / before:.2f}x): the part of the ratio that is the gusts'"
    ]


def tracking_errors_csv(states_csv: Path) -> list[tuple[float, float]] | None:
    """(t_s, tracking error) from a scenario's states.csv (None when it cannot be read)."""
    try:
        with states_csv.open(newline="") as f:
            return [
                (float(row["t_s"]), float(row["tracking_error_m"]))
                for row in csv.DictReader(f)
                if row.get("tracking_error_m")
            ]
    except (OSError, ValueError, KeyError):
        return None
