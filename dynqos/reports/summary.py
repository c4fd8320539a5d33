"""The demo's outputs: per-scenario summary.json, time series (CSV), PNG plots, and the run's report.md
that sets the measured numbers beside the paper's Table II."""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path
from typing import Any

from dynqos.common.geometry import yaw_of
from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import ControlSource, SupervisorState
from dynqos.plan.faults import FaultWindow
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import Scenario
from dynqos.reports.machine import judge, recorded_machine
from dynqos.reports.measures import reference_errors, rmse, stats, tracking_errors
from dynqos.reports.outcomes import log_times, outcome, time_in_states
from dynqos.reports.tasks import task_figures

# the cell's running totals behind each rate: figure -> (its records' table, the total, bits per unit);
# a bearer's offered bytes are those its UE buffer admitted
CELL_TOTALS = {
    "uav_admitted": ("bearers", "offered_bytes", 8),
    "uav_delivered": ("bearers", "delivered_bytes", 8),
    "uav_dropped": ("bearers", "dropped_bytes", 8),
    "bg_offered": ("background", "offered_bits", 1),
    "bg_delivered": ("background", "delivered_bits", 1),
}


def cell_rates(
    cell: list[dict[str, Any]], start_ns: int, end_ns: int, scale: float
) -> dict[str, float | None]:
    """The cell's rates over [start, end] at full scale: what the drone's bearers took in, delivered and
    dropped (a full UE buffer), the background user's, and what the uplink could carry (a trace's
    capacity is what it carried, whoever used it; None from a cell that does not count it)."""
    inside = [c for c in cell if start_ns <= c["now_ns"] <= end_ns]
    if len(inside) < 2:
        return {f"{name}_mbps": None for name in (*CELL_TOTALS, "uplink_capacity")}
    first, last = inside[0], inside[-1]
    to_mbps = scale / ((last["now_ns"] - first["now_ns"]) / 1e9) / 1e6

    def bits(c: dict[str, Any], table: str, total: str, unit: int) -> float:
        return float(sum(item[total] for item in c[table].values())) * unit

    rates: dict[str, float | None] = {
        f"{name}_mbps": (bits(last, *counter) - bits(first, *counter)) * to_mbps
        for name, counter in CELL_TOTALS.items()
    }
    counted = "capacity_bits" in first and "capacity_bits" in last
    rates["uplink_capacity_mbps"] = (
        (last["capacity_bits"] - first["capacity_bits"]) * to_mbps if counted else None
    )
    return rates


def _cpu(rec: Recording) -> dict[str, Any]:
    """`cpu_s`: each process's CPU seconds over its whole life (start-up included); `cpu_s_flight`, when
    the flight's start was read: over the recorded flight alone (from offloading to the end; a process
    restarted in it, e.g. by a site kill, from its restart)."""
    if not rec.cpu_s_t0:
        return {"cpu_s": rec.cpu_s}
    flight = {}
    for name, end in rec.cpu_s.items():
        start = rec.cpu_s_t0.get(name, 0.0)
        flight[name] = round(end - start if end >= start else end, 2)
    return {"cpu_s": rec.cpu_s, "cpu_s_flight": flight}


def _cells(scenario: Scenario, rec: Recording, start_ns: int, end_ns: int) -> dict[str, Any]:
    """The cell's rates over [start, end] (`_with_trace`) and, with two sites, `cells`: each further
    cell's rates over the same span (site -> rates; the first cell's are the summary's own)."""
    rates = _with_trace(scenario, cell_rates(rec.cell, start_ns, end_ns, scenario.scale))
    if rec.more_cells:
        more = rec.more_cells.items()
        rates["cells"] = {site: cell_rates(c, start_ns, end_ns, scenario.scale) for site, c in more}
    return rates


def _app_offered_mbps(
    statuses: list[SupervisorStatus], start_ns: int, end_ns: int, scale: float
) -> float | None:
    """What the drone's application handed to zenoh in [start, end], at full scale: every uplink message
    (camera, state, status, QoS request; from the status's running count), before zenoh, the kernel or
    the cell could drop or hold any. Statuses of a drone that does not count them give its camera bytes."""
    inside = [s for s in statuses if start_ns <= s.stamp_ns <= end_ns]
    if len(inside) < 2 or inside[-1].stamp_ns <= inside[0].stamp_ns:
        return None
    first, last = inside[0], inside[-1]
    if last.uplink_bytes:
        counted = last.uplink_bytes - first.uplink_bytes
    else:
        counted = last.camera_bytes - first.camera_bytes
    return counted * 8 / ((last.stamp_ns - first.stamp_ns) / 1e9) / 1e6 * scale


def _samples(statuses: list[SupervisorStatus], every: str, last: str) -> list[tuple[int, float]]:
    """Every latency sample the drone measured, stamped with the status that carried it.

    A status carries all samples since the one before (20 Hz of RTTs in 5 Hz of statuses). Statuses
    without that list (a recording made by hand, or by an older drone) give the latest sample of each.
    """
    if any(getattr(s, every) for s in statuses):
        return [(s.stamp_ns, v) for s in statuses for v in getattr(s, every)]
    return [(s.stamp_ns, v) for s in statuses if (v := getattr(s, last)) is not None]


def summarise(
    scenario: Scenario, rec: Recording, onboard_log: str, *, ok: bool, failure: str
) -> dict[str, Any]:
    ok, failure = judge(ok, failure, machine := recorded_machine(rec))
    t0 = rec.t0_ns
    end_ns = max([s.stamp_ns for _, s in rec.states], default=t0)
    settle_ns = t0 + round(scenario.settle_s * 1e9)
    bg_ns = rec.bg_on_ns
    baseline_end = bg_ns if bg_ns is not None else end_ns
    loaded_start = bg_ns if bg_ns is not None else settle_ns

    def window(items: list[tuple[int, float]], start: int | None, stop: int) -> list[float]:
        return [] if start is None else [v for t, v in items if start <= t < stop]

    rtts = _samples(rec.status, "rtt_samples_ms", "rtt_ms")
    cams = _samples(rec.status, "camera_latency_samples_ms", "camera_latency_ms")
    errors = [(t0 + round(t * 1e9), e) for t, e in tracking_errors(rec)]
    loaded = bg_ns is not None
    rates = _cells(scenario, rec, loaded_start, end_ns + 1)
    statuses = sorted(rec.status, key=lambda s: s.stamp_ns)
    times = dict.fromkeys((s.value for s in SupervisorState), 0.0) | time_in_states(statuses, since_ns=t0)
    first_switch, switch_cause = _first_qos_switch(statuses, bg_ns if scenario.qos == "dynamic" else None)
    gaps = [s.setpoint_gap_ms for s in statuses if s.setpoint_gap_ms is not None]
    return {
        "scenario": scenario.name,
        "profile": scenario.profile,
        "description": scenario.description,
        "qos": scenario.qos,
        "mission": scenario.mission,
        "duration_s": scenario.duration_s,
        "scale": scenario.scale,
        "bg_start_s": (bg_ns - t0) / 1e9 if bg_ns is not None else None,
        "settle_s": scenario.settle_s,
        "seed": scenario.seed,
        "bg_mbps": scenario.bg_mbps if loaded else 0.0,
        "rates_span": "loaded" if loaded else "whole run after settling",
        "uav_offered_mbps": _app_offered_mbps(statuses, loaded_start, end_ns, scenario.scale),
        **rates,
        "rtt_ms": {
            "baseline": stats(window(rtts, settle_ns, baseline_end)),
            "loaded": stats(window(rtts, bg_ns, end_ns + 1)) if loaded else None,
        },
        "camera_latency_ms": {
            "baseline": stats(window(cams, settle_ns, baseline_end)),
            "loaded": stats(window(cams, bg_ns, end_ns + 1)) if loaded else None,
        },
        "uplink_state_latency_ms": stats([lat for lat, s in rec.states if s.stamp_ns >= settle_ns]),
        "tracking_rmse_m": {
            "baseline": rmse(window(errors, settle_ns, baseline_end)),
            "loaded": rmse(window(errors, bg_ns, end_ns + 1)) if loaded else None,
        },
        "states_time_s": times,
        "transitions": _transitions(statuses, t0),
        "first_qos_switch_after_bg_s": first_switch,
        "first_qos_switch_cause": switch_cause,
        "hl_fraction_baseline": _hl_fraction(statuses, settle_ns, baseline_end),
        "camera_fps": {
            "configured": scenario.camera_fps,
            "baseline": _acked_fps(cams, settle_ns, baseline_end),
            "loaded": _acked_fps(cams, bg_ns, end_ns) if loaded else None,
        },
        "qos_network": _qos_network(
            scenario, statuses, rtts, bg_ns, window(rtts, settle_ns, baseline_end), rec.qod
        ),
        **_fallbacks(statuses, t0),
        "radio": radio_figures(statuses, t0),
        "fc_said": fc_said(statuses, t0),
        "setpoint_gap_max_ms": max(gaps) if gaps else None,
        "states_recorded": len(rec.states),
        "faults": [
            outcome(w, log_times(onboard_log), statuses, nxt.start_ns if nxt else None, errors)
            for w, nxt in itertools.zip_longest(rec.faults, rec.faults[1:])
        ],
        "tasks": task_figures(statuses, settle_ns, bg_ns, end_ns, _fault_spans(rec.faults, end_ns)),
        "memory_mb": {name: memory_figures(samples) for name, samples in rec.memory_kb.items()},
        **_cpu(rec),
        "machine": machine,  # how busy all cores were over the recorded flight
        "ok": ok,
        "failure": failure,
    }


def _fault_spans(windows: list[FaultWindow], end_ns: int) -> list[tuple[str, int, int]]:
    return [(w.fault.kind, w.start_ns, w.end_ns or end_ns) for w in windows]


def _transitions(statuses: list[SupervisorStatus], t0_ns: int) -> list[dict[str, Any]]:
    """Each supervisor transition in the recorded flight, once (every status repeats the last one)."""
    out = []
    seen = set()
    for s in statuses:
        if s.changed_ns and s.changed_ns not in seen and s.changed_ns >= t0_ns and s.cause:
            seen.add(s.changed_ns)
            out.append(
                {"t_s": (s.changed_ns - t0_ns) / 1e9, "from": s.prev_state, "to": s.state, "cause": s.cause}
            )
    return out


def _fallbacks(statuses: list[SupervisorStatus], t0_ns: int) -> dict[str, Any]:
    """Whether the drone handed over to its fallback PID during the recorded flight. A status counts the
    hand-overs since the daemon started, take-off included; those before the flight's t=0 (a watchdog
    tick while climbing to the mission) are reported on their own, not as the flight's."""
    before = [s for s in statuses if s.stamp_ns < t0_ns]
    during = [s for s in statuses if s.stamp_ns >= t0_ns]
    at_start = before[-1].fallbacks if before else 0
    in_flight = max(s.fallbacks for s in during) - at_start if during else 0
    flown_s = during[-1].fallback_s - (before[-1].fallback_s if before else 0.0) if during else 0.0
    return {
        "fallback_entered": in_flight > 0,
        "fallbacks": {"before_flight": at_start, "in_flight": in_flight},
        # as the drone counted it (statuses lost while a site was down do not hide it)
        "fallback_flown_s": round(flown_s, 2),
    }


def radio_figures(statuses: list[SupervisorStatus], t0_ns: int) -> dict[str, Any]:
    """What the drone's modem reported over the flight (docs/radio.md), and how long the fallback PID
    flew it: a coverage hole shows in both."""
    flown = [s for s in statuses if s.stamp_ns >= t0_ns]
    sinr = [s.sinr_db for s in flown if s.sinr_db is not None]
    rsrp = [s.rsrp_dbm for s in flown if s.rsrp_dbm is not None]
    controls = time_in_states(flown, field="control_source")
    return {
        "readings": len(sinr),
        "sinr_db": stats(sinr),
        "sinr_min_db": min(sinr, default=None),
        "rsrp_min_dbm": min(rsrp, default=None),
        "fallback_s": controls.get(ControlSource.FALLBACK.value, 0.0),
    }


FC_SAID_KEPT = 20


def fc_said(statuses: list[SupervisorStatus], t0_ns: int) -> list[dict[str, Any]]:
    """What the flight controller said (PX4's STATUSTEXTs and events, as the drone's status carried
    them): each text once, when it first came (s from the flight's start; negative: before take-off)
    and its MAV_SEVERITY, the first FC_SAID_KEPT."""
    said: dict[str, dict[str, Any]] = {}
    for s in statuses:
        if s.fc_text and s.fc_text not in said and len(said) < FC_SAID_KEPT:
            t_s = round((s.stamp_ns - t0_ns) / 1e9, 2)
            said[s.fc_text] = {"t_s": t_s, "severity": s.fc_severity, "text": s.fc_text}
    return list(said.values())


def memory_figures(samples: list[tuple[float, int, int]]) -> dict[str, float | None]:
    """One process's resident memory over the flight: VmRSS (`first` ... `last`) and, beside it, the
    anonymous part (`anon_*`), which a leak would move and a freshly installed library's pages do not."""
    figures: dict[str, float | None] = {}
    for prefix, column in (("", 1), ("anon_", 2)):
        figures[f"{prefix}first"] = samples[0][column] / 1024
        figures[f"{prefix}after_1min"] = next((s[column] / 1024 for s in samples if s[0] >= 60), None)
        figures[f"{prefix}max"] = max(s[column] for s in samples) / 1024
        figures[f"{prefix}last"] = samples[-1][column] / 1024
    return figures


def _first_qos_switch(statuses: list[SupervisorStatus], bg_ns: int | None) -> tuple[float | None, str | None]:
    """Seconds from the load's start to the drone's first move to the priority flow, and the cause the
    supervisor gave for it. A drone already on the priority flow when the load started (for risk) did
    not react to the load: 0.0, with the cause of the earlier move and "before the load" saying so."""
    if bg_ns is None:
        return None, None
    before = [s for s in statuses if s.stamp_ns < bg_ns]
    if before and before[-1].flow == "priority":
        return 0.0, f"before the load: {before[-1].cause or 'unknown'}"
    after = [s for s in statuses if s.stamp_ns >= bg_ns and s.flow == "priority"]
    if not after:
        return None, None
    changed = after[0].changed_ns if after[0].changed_ns >= bg_ns else after[0].stamp_ns
    return (changed - bg_ns) / 1e9, after[0].cause or "unknown"


RTT_BACK_FACTOR = 1.2  # "back": the mean of the next RTTs within this factor of the unloaded mean...
RTT_BACK_SAMPLES = 10  # ...over this many samples (0.5 s of states), so one jittery sample is not "high"


def _qos_network(
    scenario: Scenario,
    statuses: list[SupervisorStatus],
    rtts: list[tuple[int, float]],
    bg_ns: int | None,
    baseline: list[float],
    qod: dict[str, Any] | None,
) -> dict[str, Any]:
    """What the network made of the drone's priority: from the supervisor's first move to the priority flow
    under load, how long until the network's grant was AVAILABLE and until the mean of the next ten RTTs
    was back within 1.2x of the unloaded mean; the grant at the end; and the QoD sessions the emulated
    operator saw."""
    out: dict[str, Any] = {
        "backend": scenario.qos_backend,
        "decision_to_available_s": None,
        "decision_to_rtt_back_s": None,
    }
    switch_s, _ = _first_qos_switch(statuses, bg_ns)  # 0.0: already on the priority flow at the load
    if bg_ns is not None and switch_s is not None:
        decided = bg_ns + round(switch_s * 1e9)
        granted = next(
            (s.stamp_ns for s in statuses if s.stamp_ns >= decided and s.qos_grant == "available"), None
        )
        out["decision_to_available_s"] = None if granted is None else (granted - decided) / 1e9
        out["decision_to_rtt_back_s"] = _rtt_back_after(rtts, decided, baseline)
    out["grant_at_end"] = statuses[-1].qos_grant.value if statuses else None
    out["agent_heard"] = any(s.qos_agent for s in statuses)
    if qod is not None and scenario.qos_backend == "nef":  # the NEF's subscriptions
        nef = qod.get("nef") or {}
        keys = ("created", "modified", "deleted", "refused", "terminated", "expired", "reports")
        out["subscriptions"] = {k: nef.get(k, 0) for k in keys} | {"open_at_end": nef.get("open", 0)}
    elif qod is not None:
        out["sessions"] = qod_sessions(qod)
    return out


def qod_sessions(qod: dict[str, Any]) -> dict[str, int]:
    """The QoD sessions an emulated operator saw (its qod.json): created, extended, deleted, refused,
    expired, conflicts, and how many were still open when every process had stopped."""
    keys = ("created", "extended", "deleted", "refused", "expired", "conflicts")
    return {k: qod.get(k, 0) for k in keys} | {"open_at_end": len(qod.get("sessions", []))}


def _with_trace(scenario: Scenario, rates: dict[str, float | None]) -> dict[str, Any]:
    """The cell's rates, with which Mahimahi trace the uplink replayed (its file's name; None: a constant
    capacity) and the share of what it could carry that reached the edge from the drone (docs/camera.md)."""
    trace = scenario.config.get("cell", {}).get("trace", "")
    delivered, capacity = rates["uav_delivered_mbps"], rates["uplink_capacity_mbps"]
    share = delivered / capacity if trace and delivered is not None and capacity else None
    return {**rates, "uplink_trace": Path(trace).name if trace else None, "uplink_share": share}


def _rtt_back_after(rtts: list[tuple[int, float]], since_ns: int, baseline: list[float]) -> float | None:
    if not baseline:
        return None
    limit = RTT_BACK_FACTOR * sum(baseline) / len(baseline)
    later = [(t, v) for t, v in rtts if t >= since_ns]
    for i in range(len(later) - RTT_BACK_SAMPLES + 1):
        if sum(v for _, v in later[i : i + RTT_BACK_SAMPLES]) <= limit * RTT_BACK_SAMPLES:
            return (later[i][0] - since_ns) / 1e9
    return None


def _hl_fraction(statuses: list[SupervisorStatus], start_ns: int, stop_ns: int) -> float | None:
    """The share of the unloaded flight's statuses in which the supervisor read high latency: with no
    load it should be none; the paper's rho2 at the paper's own unloaded RTT makes it most."""
    inside = [s for s in statuses if start_ns <= s.stamp_ns < stop_ns and s.latency != "NA"]
    return sum(s.latency == "HL" for s in inside) / len(inside) if inside else None


def _acked_fps(cams: list[tuple[int, float]], start: int | None, stop: int) -> float | None:
    """Camera frames the detector acknowledged per second in [start, stop): two acks (RGB, depth) a
    frame. Below the configured rate, the drone offered less than the scenario asks (a CPU that cannot
    render and encode that fast, or frames lost on the way)."""
    if start is None or stop <= start:
        return None
    acks = sum(1 for t, _ in cams if start <= t < stop)
    return acks / 2 / ((stop - start) / 1e9)


def write_scenario(
    folder: Path, scenario: Scenario, rec: Recording, summary: dict[str, Any], *, plots: bool = True
) -> None:
    """summary.json, states.csv, supervisor.csv, latency.csv and (plots) overview.png, supervisor.png."""
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    t0 = rec.t0_ns
    with (folder / "states.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["t_s", "x_m", "y_m", "z_m", "yaw_rad", "uplink_latency_ms", "mode", "tracking_error_m"]
        )
        errors = dict(reference_errors((s for _, s in rec.states), rec.refs))
        for lat, st in rec.states:
            error = errors.get(st.stamp_ns)
            t_s, yaw = f"{(st.stamp_ns - t0) / 1e9:.3f}", f"{yaw_of(st.quat):.4f}"
            writer.writerow(
                [t_s, *st.pos_m, yaw, f"{lat:.3f}", st.mode, "" if error is None else f"{error:.4f}"]
            )
    columns = [
        "state",
        "flow",
        "camera_flow",
        "camera_rate_factor",
        "control_source",
        "latency",
        "risk",
        "watchdog",
        "rtt_ms",
        "camera_latency_ms",
        "t_cc_ms",
        "t_cam_ms",
        "p_cc",
        "p_cam",
        "p_lat",
        "p_cs",
        "spaciousness_m",
    ]
    with (folder / "supervisor.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["t_s", *columns])
        for sv in rec.status:
            writer.writerow([f"{(sv.stamp_ns - t0) / 1e9:.3f}", *(getattr(sv, c) for c in columns)])
    with (folder / "latency.csv").open("w", newline="") as f:  # every sample, at its status's time
        writer = csv.writer(f)
        writer.writerow(["t_s", "kind", "ms"])
        for sv in rec.status:
            t_s = f"{(sv.stamp_ns - t0) / 1e9:.3f}"
            writer.writerows([t_s, "rtt", v] for v in sv.rtt_samples_ms)
            writer.writerows([t_s, "camera", v] for v in sv.camera_latency_samples_ms)
    if plots:
        from dynqos.reports.plots import plot_flight

        plot_flight(folder, scenario, rec, summary["bg_start_s"])
