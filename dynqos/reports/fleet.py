"""A fleet run's summary and files: each drone's figures (the single-drone contract, from its own
streams and the cell's counters of its own bearers), the QoS agent's decisions, and a timeline of
grants over risk and latency (docs/fleet.md)."""

from __future__ import annotations

import csv
import itertools
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.messages import QosDecision, SupervisorStatus
from dynqos.onboard.supervisor import PRIORITY_STATES as SUPERVISOR_PRIORITY_STATES
from dynqos.onboard.supervisor import RATE_ADAPTATION_STATES as SUPERVISOR_RATE_ADAPTATION_STATES
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import Scenario, run_id
from dynqos.reports.figures import figure
from dynqos.reports.machine import describe, judge, recorded_machine
from dynqos.reports.multipath import fault_spans, path_figures
from dynqos.reports.outcomes import time_in_states
from dynqos.reports.summary import cell_rates, summarise, write_scenario

# What each drone's entry carries of the single-drone summary.
DRONE_FIELDS = (
    "uav_offered_mbps",
    "uav_admitted_mbps",
    "uav_delivered_mbps",
    "rtt_ms",
    "camera_latency_ms",
    "tracking_rmse_m",
    "states_time_s",
    "transitions",
    "first_qos_switch_after_bg_s",
    "camera_fps",
    "fallback_entered",
    "setpoint_gap_max_ms",
    "states_recorded",
    "faults",
    "radio",
    "fc_said",
)
PRIORITY_STATES = sorted(s.value for s in SUPERVISOR_PRIORITY_STATES)  # q2, q3, q5, q6
RATE_ADAPTATION_STATES = sorted(s.value for s in SUPERVISOR_RATE_ADAPTATION_STATES)  # q4, q5, q6
RTT_LIMIT = 1.2  # a high-risk drone's loaded RTT mean within this factor of its own baseline...
DELIVERED_SHARE = 0.95  # ...delivering at least this share of what it put into its bearers...
GAP_LIMIT_MS = 100.0  # ...and no drone's setpoints paused longer than this


def drone_recording(rec: Recording, uav: str, own: Recording) -> Recording:
    """One drone's view of the fleet's recording: its own streams, the cell's counters of its own
    bearers (the background's are the cell's), the shared load and time zero."""
    cell = [
        {**c, "bearers": {k: v for k, v in c["bearers"].items() if k.startswith(f"{uav}-")}} for c in rec.cell
    ]
    return replace(own, cell=cell, t0_ns=rec.t0_ns, bg_on_ns=rec.bg_on_ns, offload_ns=rec.t0_ns)


def _spans(statuses: list[SupervisorStatus], since_ns: int, field: str) -> dict[str, float]:
    return {k: round(v, 2) for k, v in sorted(time_in_states(statuses, since_ns, field).items())}


def _drone(
    scenario: Scenario, rec: Recording, uav: str, own: Recording, log: str, ok: bool
) -> dict[str, Any]:
    view = drone_recording(rec, uav, own)
    single = summarise(scenario, view, log, ok=ok, failure="")
    zone = next(d.risk_zone for d in scenario.drones if d.id == uav)
    statuses = sorted(view.status, key=lambda s: s.stamp_ns)
    out = {k: single[k] for k in DRONE_FIELDS}
    out["risk_zone"] = zone
    out["priority_time_s"] = round(sum(single["states_time_s"].get(q, 0.0) for q in PRIORITY_STATES), 2)
    out["granted_time_s"] = _spans(statuses, rec.t0_ns, "qos_grant").get("available", 0.0)
    out["risk_time_s"] = _spans(statuses, rec.t0_ns, "risk")
    out["rate_adaptation_time_s"] = round(
        sum(single["states_time_s"].get(q, 0.0) for q in RATE_ADAPTATION_STATES), 2
    )
    base, loaded = single["rtt_ms"]["baseline"], single["rtt_ms"]["loaded"]
    out["rtt_loaded_over_baseline"] = (
        loaded["mean"] / base["mean"] if base and loaded and base.get("mean") and loaded.get("mean") else None
    )
    admitted, delivered = single["uav_admitted_mbps"], single["uav_delivered_mbps"]
    out["delivered_share"] = delivered / admitted if admitted and delivered is not None else None
    out["cell_queue_ms"] = _queue_delays(rec, uav)
    out["fallback_flown_s"] = single["fallback_flown_s"]
    if scenario.sites == 2:  # a drone on two paths (docs/multipath.md)
        out["multipath"] = path_figures(statuses, rec.t0_ns, *fault_spans(rec.faults))
    if single["tasks"]:  # the drone's own offloaded tasks (docs/offload.md)
        out["tasks"] = single["tasks"]
    return out


def _queue_delays(rec: Recording, uav: str) -> dict[str, float | None]:
    """The mean queue delay of each of the drone's bearers in the cell while the load lasted (the cell's
    own figure, sampled by the flight loop): the network's part of the drone's latency, though a sender
    that stalls on a busy CPU and then bursts queues there too. None where there is no sample."""
    start = rec.bg_on_ns if rec.bg_on_ns is not None else rec.t0_ns
    out: dict[str, float | None] = {}
    for flow in ("default", "priority"):
        values = [
            float(c["bearers"][name]["queue_delay_ms"])
            for c in rec.cell
            if c["now_ns"] >= start and (name := f"{uav}-{flow}") in c["bearers"]
        ]
        out[flow] = sum(values) / len(values) if values else None
    return out


def summarise_fleet(
    scenario: Scenario,
    rec: Recording,
    recs: dict[str, Recording],
    decisions: list[QosDecision],
    onboard_logs: dict[str, str],
    *,
    ok: bool,
    failure: str,
) -> dict[str, Any]:
    machine = recorded_machine(rec)
    ok, failure = judge(ok, failure, machine)
    drones = {uav: _drone(scenario, rec, uav, recs[uav], onboard_logs.get(uav, ""), ok) for uav in recs}
    end_ns = max((s.stamp_ns for r in recs.values() for _, s in r.states), default=rec.t0_ns)
    loaded_start = rec.bg_on_ns if rec.bg_on_ns is not None else rec.t0_ns
    cell = cell_rates(rec.cell, loaded_start, end_ns + 1, scenario.scale)
    counts = {a: sum(d.action == a for d in decisions) for a in ("grant", "deny", "revoke", "release")}
    faults = _faults(rec, drones)
    checks = _checks(rec, drones, faults)
    qod = rec.qod or {}
    memory = rec.memory_kb.items()  # name -> (t_s, VmRSS kB, RssAnon kB)
    arbiter = None
    if scenario.qos_policy == "arbiter":
        arbiter = {
            "grants": counts["grant"],
            "denials": counts["deny"],
            "revocations": counts["revoke"],
            "releases": counts["release"],
        }
    return {
        "scenario": scenario.name,
        "profile": scenario.profile,
        "description": scenario.description,
        "fleet": True,
        "qos": scenario.qos,
        "qos_backend": scenario.qos_backend,
        "qos_policy": scenario.qos_policy,
        "arbiter_max_grants": scenario.arbiter_max_grants,
        "duration_s": scenario.duration_s,
        "scale": scenario.scale,
        "seed": scenario.seed,
        "bg_start_s": (rec.bg_on_ns - rec.t0_ns) / 1e9 if rec.bg_on_ns is not None else None,
        "bg_mbps": scenario.bg_mbps if rec.bg_on_ns is not None else 0.0,
        "bg_weight": scenario.bg_weight,
        "uav_mbps_each": scenario.uav_mbps,
        "bg_offered_mbps": cell["bg_offered_mbps"],
        "bg_delivered_mbps": cell["bg_delivered_mbps"],
        "drones_delivered_mbps": cell["uav_delivered_mbps"],
        "drones": drones,
        "arbiter": arbiter,
        "qod_sessions": {
            k: qod.get(k, 0) for k in ("created", "extended", "deleted", "refused", "expired", "conflicts")
        }
        | {"open_at_end": len(qod.get("sessions", []))},
        "checks": checks,
        "faults": faults,
        "cpu_s": rec.cpu_s,
        "machine": machine,
        "memory_mb": {name: max(s[1] for s in samples) / 1024 for name, samples in memory},
        "anon_memory_mb": {name: max(s[2] for s in samples) / 1024 for name, samples in memory},
        "ok": ok,
        "failure": failure,
    }


def _checks(
    rec: Recording, drones: dict[str, dict[str, Any]], faults: list[dict[str, Any]]
) -> dict[str, bool]:
    """What a fleet's flight must show: the arbiter's bar for the high-risk drones under load, steady
    setpoints, every drone heard, and no fallback in the edge's faults."""
    high = {u: d for u, d in drones.items() if d["risk_zone"] == "high"}
    gaps = [d["setpoint_gap_max_ms"] for d in drones.values() if d["setpoint_gap_max_ms"] is not None]
    checks: dict[str, bool] = (
        {}
        if rec.bg_on_ns is None
        else {  # the arbiter's bar is for a loaded cell
            "high_risk_rtt_within_1_2x": all(
                d["rtt_loaded_over_baseline"] is not None and d["rtt_loaded_over_baseline"] <= RTT_LIMIT
                for d in high.values()
            ),
            "high_risk_delivered_95pct": all(
                d["delivered_share"] is not None and d["delivered_share"] >= DELIVERED_SHARE
                for d in high.values()
            ),
        }
    )
    checks["setpoint_gaps_within_100ms"] = bool(gaps) and max(gaps) <= GAP_LIMIT_MS
    # a drone whose link never carried a state during the flight (stuck in a coverage hole, say) has no
    # figures at all: the run says so rather than leaving a quiet entry
    checks["every_drone_heard"] = all(d["states_recorded"] > 0 for d in drones.values())
    if faults:  # the edge's faults (replicas killed, hung) must not send any drone to its fallback
        checks["no_fallback_in_faults"] = not any(f["fallback"] for f in faults)
    return checks


def _faults(rec: Recording, drones: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Each fault, with what it did on every drone (each drone's own outcome is in its entry)."""
    out = []
    for i, window in enumerate(rec.faults):
        outcomes = {uav: d["faults"][i] for uav, d in drones.items()}
        gaps = [o["max_setpoint_gap_ms"] for o in outcomes.values() if o["max_setpoint_gap_ms"] is not None]
        out.append(
            {
                "kind": window.fault.kind,
                "at_s": window.fault.at_s,
                "duration_s": window.fault.duration_s,
                "target": window.target,
                "notes": window.notes,
                "fell_back": sorted(uav for uav, o in outcomes.items() if o["fallback"]),
                "fallback": any(o["fallback"] for o in outcomes.values()),
                "max_setpoint_gap_ms": max(gaps) if gaps else None,
                **({"grant": window.grant} if window.grant is not None else {}),
            }
        )
    return out


def write_fleet(
    folder: Path,
    scenario: Scenario,
    rec: Recording,
    recs: dict[str, Recording],
    decisions: list[QosDecision],
    summary: dict[str, Any],
) -> None:
    """summary.json, each drone's CSVs in <uav>/, decisions.csv and timeline.png."""
    for uav, own in recs.items():
        sub = folder / uav
        sub.mkdir(exist_ok=True)
        write_scenario(sub, scenario, drone_recording(rec, uav, own), summary["drones"][uav], plots=False)
    with (folder / "decisions.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t_s", "uav", "action", "risk", "latency_excess", "holders", "reason"])
        for d in decisions:
            writer.writerow(
                [
                    f"{(d.stamp_ns - rec.t0_ns) / 1e9:.3f}",
                    d.uav,
                    d.action,
                    d.risk,
                    f"{d.latency_excess:.2f}",
                    " ".join(d.holders),
                    d.reason,
                ]
            )
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    _timeline(folder, scenario, rec, recs, summary)


RISK_COLOURS = {"HR": "tab:red", "MR": "tab:orange", "LR": "tab:green", "NA": "lightgray"}
GRANT_COLOURS = {"available": "tab:green", "requested": "gold", "unavailable": "tab:red"}


def _timeline(
    folder: Path, scenario: Scenario, rec: Recording, recs: dict[str, Recording], summary: dict[str, Any]
) -> None:
    """One row per drone: its C&C RTT, with a strip for its risk level and one for the network's grant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0, bg = rec.t0_ns, summary["bg_start_s"]
    fig, axes = plt.subplots(len(recs), 1, figsize=(12, 2.2 * len(recs)), sharex=True, squeeze=False)
    for ax, (uav, own) in zip(axes[:, 0], recs.items(), strict=True):
        statuses = sorted((s for s in own.status if s.stamp_ns >= t0), key=lambda s: s.stamp_ns)
        rtt = [((s.stamp_ns - t0) / 1e9, v) for s in statuses for v in s.rtt_samples_ms[-1:]]
        ax.plot([t for t, _ in rtt], [v for _, v in rtt], lw=1, color="tab:blue", label="C&C RTT")
        ax.set_yscale("log")
        top = ax.get_ylim()[1]
        for a, b in itertools.pairwise(statuses):
            x0, x1 = (a.stamp_ns - t0) / 1e9, (b.stamp_ns - t0) / 1e9
            ax.axvspan(x0, x1, ymin=0.93, ymax=1.0, color=RISK_COLOURS.get(a.risk, "lightgray"), lw=0)
            colour = GRANT_COLOURS.get(a.qos_grant.value)
            if colour:
                ax.axvspan(x0, x1, ymin=0.85, ymax=0.92, color=colour, lw=0)
        if bg is not None:
            ax.axvline(bg, color="k", ls="--", lw=1)
        zone = summary["drones"][uav]["risk_zone"]
        ax.set_ylabel(f"{uav}\n({zone} risk)\nRTT ms", fontsize=8)
        ax.set_ylim(top=top * 3)
    axes[-1, 0].set_xlabel("t (s); dashed: background load on")
    fig.suptitle(
        f"{scenario.name}: top strip risk (red HR, orange MR, green LR), below it the grant "
        "(green available, yellow requested, red unavailable)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(folder / "timeline.png", dpi=90)
    plt.close(fig)


# ---- report.md ------------------------------------------------------------------------------------------


def _f(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def fleet_section(s: dict[str, Any]) -> list[str]:
    """One fleet scenario: its setting, a row per drone, the arbiter's counts and the timeline. Figures
    of a repeated scenario are mean [95% interval] over its runs."""
    first = s["runs"][0] if "aggregate" in s else s
    name = run_id(first["scenario"], first.get("profile", "dynqos"))
    runs = f" ({len(s['runs'])} runs)" if "aggregate" in s else ""
    policy = first["qos_policy"]
    if policy == "arbiter":
        policy += f", at most {first['arbiter_max_grants']} grants"
    lines = [
        f"### {name}{runs}",
        "",
        first["description"],
        "",
        f"- qos {first['qos']}, backend {first['qos_backend']}, policy {policy}; each drone sized to offer "
        f"{_f(first['uav_mbps_each'])} Mbit/s; background {_f(first['bg_mbps'], 0)} Mbit/s at weight "
        f"{_f(first['bg_weight'], 0)} from {figure(s, 'bg_start_s')} s, delivered "
        f"{figure(s, 'bg_delivered_mbps')} Mbit/s",
        "",
        "| drone | risk zone | offered / delivered (Mbit/s) | RTT mean baseline / loaded (ms) "
        "| RMSE baseline / loaded (m) | in priority (s) | granted (s) | rate adaptation (s) | in qA (s) "
        "| largest setpoint gap (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for uav, d in first["drones"].items():
        p = f"drones.{uav}."
        lines.append(
            f"| {uav} | {d['risk_zone']} | {figure(s, p + 'uav_offered_mbps')} / "
            f"{figure(s, p + 'uav_delivered_mbps')} | {figure(s, p + 'rtt_ms.baseline.mean')} / "
            f"{figure(s, p + 'rtt_ms.loaded.mean')} | {figure(s, p + 'tracking_rmse_m.baseline', 3)} / "
            f"{figure(s, p + 'tracking_rmse_m.loaded', 3)} | {figure(s, p + 'priority_time_s')} "
            f"| {figure(s, p + 'granted_time_s')} | {figure(s, p + 'rate_adaptation_time_s')} "
            f"| {figure(s, p + 'states_time_s.qA')} | {figure(s, p + 'setpoint_gap_max_ms')} |"
        )
    lines.append("")
    if first.get("arbiter"):
        lines.append(
            f"- arbiter: {figure(s, 'arbiter.grants', 0)} grants, {figure(s, 'arbiter.denials', 0)} denials, "
            f"{figure(s, 'arbiter.revocations', 0)} revocations, {figure(s, 'arbiter.releases', 0)} releases"
        )
    cpu = first["cpu_s"]
    lines += [
        f"- QoD sessions: {figure(s, 'qod_sessions.created', 0)} created, "
        f"{figure(s, 'qod_sessions.open_at_end', 0)} open at the end",
        "- checks: "
        + ", ".join(f"{k} {v}" for k, v in first["checks"].items())
        + (" (first run)" if runs else ""),
        f"- CPU seconds: {_f(sum(cpu.values()))} over every process "
        f"({', '.join(f'{k} {v:.1f}' for k, v in sorted(cpu.items()))})" + (" (first run)" if runs else ""),
        *[
            f"- {'seed ' + str(run.get('seed')) + ': ' if runs else ''}{describe(run.get('machine'))}"
            for run in (s["runs"] if runs else [s])
        ],
        *_fault_lines(s, first),
        f"- ok: {s['ok']} {s['failure']}",
        "",
    ]
    if not runs:
        lines += [f"![{name} timeline]({name}/timeline.png)", ""]
    return lines


def _fault_lines(s: dict[str, Any], first: dict[str, Any]) -> list[str]:
    """Each fault: its target, which drones fell back (in how many runs), the longest setpoint pause."""
    runs = s["runs"] if "aggregate" in s else [s]
    lines = []
    for i, f in enumerate(first.get("faults", [])):
        fell = [run["faults"][i]["fell_back"] for run in runs]
        who = "no drone fell back"
        if any(fell):
            who = "fell back: " + "; ".join(", ".join(x) or "-" for x in fell)
            who += f" (in {sum(map(bool, fell))} of {len(runs)} runs)" if len(runs) > 1 else ""
        lines.append(
            f"- fault {f['kind']} at {f['at_s']:g} s for {f['duration_s']:g} s on {f['target'] or '-'}: {who}"
            f"; longest setpoint gap {figure(s, f'faults.{i}.max_setpoint_gap_ms')} ms"
        )
    return lines


def fleet_comparison(fleets: list[dict[str, Any]]) -> list[str]:
    """What the high-risk drones kept under each policy: the measured form of the paper's warning."""
    firsts = [s["runs"][0] if "aggregate" in s else s for s in fleets]
    high = sorted({u for s in firsts for u, d in s["drones"].items() if d["risk_zone"] == "high"})
    if not high or len(fleets) < 2:
        return []
    lines = [
        "### The high-risk drones under each policy",
        "",
        "| drone | " + " | ".join(s["scenario"] for s in firsts) + " |",
        "|---|" + "---|" * len(fleets),
    ]
    for uav in high:
        cells = []
        for s in fleets:
            p = f"drones.{uav}."
            cells.append(
                f"offered {figure(s, p + 'uav_offered_mbps')} Mbit/s, "
                f"RTT {figure(s, p + 'rtt_ms.loaded.mean')} ms "
                f"({figure(s, p + 'rtt_loaded_over_baseline', 2)}x), "
                f"{figure(s, p + 'rate_adaptation_time_s')} s rate-adapted"
            )
        lines.append(f"| {uav} | " + " | ".join(cells) + " |")
    return [*lines, ""]
