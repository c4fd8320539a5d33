"""`dynqos demo` and `dynqos run FILE`: the paper's experiment, scenario after scenario, on one machine.

Each scenario runs as real processes (dynqos/experiment/runner.py); the demo applies the command line's
overrides, stops cleanly on Ctrl-C, and writes summary.json and the report over all scenarios
(dynqos/reports/summary.py).
"""

from __future__ import annotations

import json
import logging
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.errors import ConfigError
from dynqos.experiment.machine import SIZED_FOR_CORES, machine_said
from dynqos.experiment.profile import DEFAULT_PROFILE, Profile, load_profile
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import Scenario, builtin_scenario
from dynqos.reports.aggregate import repeated_summary
from dynqos.reports.figures import figure
from dynqos.reports.markdown import write_report

log = logging.getLogger(__name__)


MAX_REPEAT = 50


def run_demo(
    names: list[str],
    out: Path,
    *,
    duration_s: float | None,
    scale: float | None,
    seed: int | None,
    scenarios: list[Scenario] | None = None,
    profiles: list[Profile] | None = None,
    repeat: int = 1,
    metrics_port: int = 0,
    vehicle: dict[str, Any] | None = None,
    qos_backend: str | None = None,
    trace: str | None = None,
) -> dict[str, Any]:
    """Every scenario under every profile, each `repeat` times with seeds seed, seed + 1, ...; then
    summary.json over all of them and report.md. `qos_backend`: the scenarios' own when None; `trace`:
    a Mahimahi uplink trace every scenario's cell replays (the scenario's own, if any, when None)."""
    if not 1 <= repeat <= MAX_REPEAT:
        raise ConfigError("--repeat", f"must be in 1..{MAX_REPEAT}, got {repeat}")
    chosen = scenarios if scenarios is not None else [builtin_scenario(n) for n in names]
    chosen = _traced(chosen, trace)
    runs = [
        profile.apply(scenario)
        for scenario in _overridden(chosen, duration_s, scale, seed, metrics_port, vehicle or {}, qos_backend)
        for profile in profiles or [load_profile(DEFAULT_PROFILE)]
    ]
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError("--out", f"cannot make the run folder {out}: {exc.strerror or exc}") from None
    stop = threading.Event()
    previous = signal.getsignal(signal.SIGINT)

    def interrupt(signum: int, _frame: object) -> None:
        log.warning("interrupted: stopping every process")
        stop.set()

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    summaries = []
    started = time.monotonic()
    machine, short = machine_said()
    if short:
        log.warning(
            "machine: %s, fewer than the %d the scenarios were sized for: a flight may be starved (its "
            "summary's `machine` says how busy its cores were)",
            machine,
            SIZED_FOR_CORES,
        )
    else:
        log.info("machine: %s", machine)
    try:
        for scenario in runs:
            if stop.is_set():
                break
            log.info("scenario %s: %s", scenario.run_id, scenario.description)
            summary = _run_repeated(scenario, out, repeat, stop)
            summaries.append(summary)
            log.info("scenario %s: ok=%s %s", scenario.run_id, summary["ok"], headline(summary))
    finally:
        signal.signal(signal.SIGINT, previous)
    top = {
        "scenarios": summaries,
        "repeat": repeat,
        "wall_time_s": time.monotonic() - started,
        "out": str(out),
        "ok": bool(summaries) and all(s["ok"] for s in summaries) and len(summaries) == len(runs),
    }
    (out / "summary.json").write_text(json.dumps(top, indent=2) + "\n")
    write_report(out, summaries)
    return top


def _traced(chosen: list[Scenario], trace: str | None) -> list[Scenario]:
    """The scenarios with `trace` as their cell's uplink trace; a scenario that sets a trace's mean
    ([cell] trace_mean_mbps) flies on a trace, and without one it is an error now."""
    result = []
    for scenario in chosen:
        cell = scenario.config.get("cell", {})
        if trace is not None:
            cell = {**cell, "trace": trace}
            scenario = replace(scenario, config={**scenario.config, "cell": cell})
        if cell.get("trace_mean_mbps") and not cell.get("trace"):
            raise ConfigError(
                "--trace",
                f"scenario {scenario.name} replays a real uplink trace as the cell's capacity: give a "
                "Mahimahi trace with --trace FILE (docs/camera.md)",
            )
        result.append(scenario)
    return result


def _overridden(
    chosen: list[Scenario],
    duration_s: float | None,
    scale: float | None,
    seed: int | None,
    metrics_port: int = 0,
    vehicle: dict[str, Any] | None = None,
    qos_backend: str | None = None,
) -> list[Scenario]:
    """The scenarios with the command line's changes; `vehicle`: {"vehicle": "px4", "px4_dir": DIR}."""
    overrides: dict[str, Any] = {"metrics_port": metrics_port} if metrics_port else {}
    if qos_backend is not None:
        overrides["qos_backend"] = qos_backend
    vehicle = vehicle or {}
    if "vehicle" in vehicle:
        overrides["vehicle"] = vehicle["vehicle"]
    if duration_s is not None:
        overrides["duration_s"] = duration_s
    if scale is not None:
        overrides["scale"] = scale
    if seed is not None:
        overrides["seed"] = seed
    result = []
    for scenario in chosen:
        changes = dict(overrides)
        if "duration_s" in changes and scenario.bg_start_s >= 0:
            changes["bg_start_s"] = changes["duration_s"] / 2
        if "px4_dir" in vehicle:
            px4 = {**scenario.config.get("px4", {}), "dir": vehicle["px4_dir"]}
            changes["config"] = {**scenario.config, "px4": px4}
        try:
            result.append(replace(scenario, **changes))
        except ConfigError as exc:
            raise exc.under(scenario.name) from None
    return result


def _run_repeated(scenario: Scenario, out: Path, repeat: int, stop: threading.Event) -> dict[str, Any]:
    """One run into out/<run id>/, or `repeat` runs into out/<run id>/seed<N>/ with the aggregate in
    out/<run id>/summary.json."""
    if repeat == 1:
        return run_scenario(scenario, out, stop=stop)
    folder = out / scenario.run_id
    runs = []
    for k in range(repeat):
        if stop.is_set():
            break
        seeded = replace(scenario, seed=scenario.seed + k)
        runs.append(run_scenario(seeded, out, folder=folder / f"seed{seeded.seed}", stop=stop))
    summary = repeated_summary(runs)
    if len(runs) < repeat:
        summary["ok"], summary["failure"] = False, summary["failure"] or "interrupted"
    (folder / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def headline(summary: dict[str, Any]) -> str:
    runs = f" over {len(summary['runs'])} runs" if "runs" in summary else ""
    if summary.get("fleet"):
        first = summary["runs"][0] if "runs" in summary else summary
        parts = []
        for uav, d in first["drones"].items():
            rtt = f"drones.{uav}.rtt_ms"
            parts.append(
                f"{uav} ({d['risk_zone']} risk) rtt baseline mean {figure(summary, rtt + '.baseline.mean')} "
                f"ms, "
                f"loaded mean {figure(summary, rtt + '.loaded.mean')} ms"
            )
        return "; ".join(parts) + runs
    return (
        f"rtt baseline mean {figure(summary, 'rtt_ms.baseline.mean')} ms, "
        f"loaded mean {figure(summary, 'rtt_ms.loaded.mean')} ms{runs}"
    )


def default_out_dir() -> Path:
    return Path("runs") / time.strftime("%Y%m%d-%H%M%S")
