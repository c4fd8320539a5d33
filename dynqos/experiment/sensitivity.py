"""`dynqos sensitivity`: where relative priority stops protecting the drone.

The paper's priority is relative: the priority bearer's scheduling weight against 1 for everyone else
(4 here), not a guaranteed rate. This flies `bg-staticqos` (the priority flow all along, so the
supervisor plays no part) once per priority weight and background load, and reports the drone's loaded
C&C RTT and delivered rate for each: a table, summary.json and sensitivity.png. With a weight w the
priority bearer's share of a full cell is w / (w + 1); once that share is below what the drone offers,
its queue grows as on the default flow.

With `repeat` N every point is flown with seeds seed..seed+N-1: each figure of the point becomes the
mean over its runs, with its 95% interval beside it (`ci95`) and every run kept (`runs`); the plot draws
the intervals.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.errors import ConfigError
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import Scenario, builtin_scenario
from dynqos.reports.aggregate import aggregate
from dynqos.reports.figures import fmt, interval_text

log = logging.getLogger(__name__)

WEIGHTS = (1.0, 2.0, 4.0, 8.0)
LOADS_MBPS = (40.0, 80.0, 120.0)
MAX_POINTS = 64
MAX_REPEAT = 20
FIGURES = (
    "rtt_baseline_mean_ms",
    "rtt_loaded_mean_ms",
    "rtt_loaded_p95_ms",
    "uav_offered_mbps",
    "uav_admitted_mbps",
    "uav_delivered_mbps",
    "bg_delivered_mbps",
)


def run_sensitivity(
    out: Path,
    *,
    weights: tuple[float, ...] = WEIGHTS,
    loads_mbps: tuple[float, ...] = LOADS_MBPS,
    duration_s: float = 20.0,
    seed: int = 0,
    repeat: int = 1,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    if not weights or not loads_mbps or len(weights) * len(loads_mbps) > MAX_POINTS:
        raise ConfigError("--weights", f"give 1..{MAX_POINTS} (weight, load) points")
    if not 1 <= repeat <= MAX_REPEAT:
        raise ConfigError("--repeat", f"must be in 1..{MAX_REPEAT}, got {repeat}")
    stop = stop or threading.Event()
    base = builtin_scenario("bg-staticqos")
    points = []
    started = time.monotonic()
    for load in loads_mbps:
        for weight in weights:
            runs = [
                _point(weight, load, run_scenario(scenario, out, stop=stop, progress=False))
                for scenario in _flights(base, weight, load, duration_s, range(seed, seed + repeat))
                if not stop.is_set()
            ]
            if runs:
                points.append(runs[0] if repeat == 1 else _repeated_point(runs))
    result = {
        "study": "sensitivity",
        "scenario": base.name,
        "duration_s": duration_s,
        "seed": seed,
        "repeat": repeat,
        "scale": base.scale,
        "points": points,
        "wall_time_s": time.monotonic() - started,
        "ok": bool(points) and all(p["ok"] for p in points),
    }
    (out / "summary.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / "sensitivity.md").write_text(markdown(result))
    _plot(out, points)
    return result


def _flights(
    base: Scenario, weight: float, load: float, duration_s: float, seeds: range
) -> Iterator[Scenario]:
    """The scenario of one (weight, load) point, once per seed (each run in its own folder)."""
    for seed in seeds:
        log.info("sensitivity: priority weight %g, background %g Mbit/s, seed %d", weight, load, seed)
        name = f"w{weight:g}-bg{load:g}" + (f"-seed{seed}" if len(seeds) > 1 else "")
        yield replace(
            base,
            name=name,
            priority_weight=weight,
            bg_mbps=load,
            duration_s=duration_s,
            bg_start_s=duration_s / 2,
            seed=seed,
        )


def _point(weight: float, load: float, summary: dict[str, Any]) -> dict[str, Any]:
    loaded = summary["rtt_ms"]["loaded"] or {}
    return {
        "priority_weight": weight,
        "bg_mbps": load,
        "share_of_full_cell": weight / (weight + 1),
        "seed": summary.get("seed"),
        "rtt_baseline_mean_ms": summary["rtt_ms"]["baseline"]["mean"],
        "rtt_loaded_mean_ms": loaded.get("mean"),
        "rtt_loaded_p95_ms": loaded.get("p95"),
        "uav_offered_mbps": summary["uav_offered_mbps"],
        "uav_admitted_mbps": summary["uav_admitted_mbps"],
        "uav_delivered_mbps": summary["uav_delivered_mbps"],
        "bg_delivered_mbps": summary["bg_delivered_mbps"],
        "ok": summary["ok"],
    }


def _repeated_point(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One point over its runs: each figure's mean at the point's top (what the table and plot read),
    its mean and 95% interval in `ci95`, and every run."""
    point: dict[str, Any] = {k: runs[0][k] for k in ("priority_weight", "bg_mbps", "share_of_full_cell")}
    figures = aggregate(runs)  # runs without a figure (None) are left out of its interval
    point["ci95"] = {name: figures.get(name) for name in FIGURES}
    point |= {name: agg["mean"] if agg else None for name, agg in point["ci95"].items()}
    point["seeds"] = [run["seed"] for run in runs]
    point["runs"] = runs
    point["ok"] = all(run["ok"] for run in runs)
    return point


def _text(point: dict[str, Any], name: str) -> str:
    agg = (point.get("ci95") or {}).get(name)
    return interval_text(agg) if agg is not None else fmt(point[name])


def markdown(result: dict[str, Any]) -> str:
    lines = [
        "# Sensitivity: priority weight and background load",
        "",
        f"`{result['scenario']}` (the priority flow all along), {result['duration_s']:g} s per point with "
        f"the load from half-way, {_seeds(result)}, scale {result['scale']:g}. Rates at full scale"
        + ("; each figure: mean over the runs [95% interval]." if result.get("repeat", 1) > 1 else "."),
        "",
        "| priority weight | share of a full cell | background (Mbit/s) | RTT before / under load (ms) "
        "| RTT p95 under load (ms) | UAV offered / delivered (Mbit/s) | background delivered (Mbit/s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in result["points"]:
        lines.append(
            f"| {p['priority_weight']:g} | {p['share_of_full_cell']:.2f} | {p['bg_mbps']:g} "
            f"| {_text(p, 'rtt_baseline_mean_ms')} / {_text(p, 'rtt_loaded_mean_ms')} "
            f"| {_text(p, 'rtt_loaded_p95_ms')} "
            f"| {_text(p, 'uav_offered_mbps')} / {_text(p, 'uav_delivered_mbps')} "
            f"| {_text(p, 'bg_delivered_mbps')} |"
        )
    lines += ["", "![sensitivity](sensitivity.png)", ""]
    return "\n".join(lines)


def _seeds(result: dict[str, Any]) -> str:
    repeat = result.get("repeat", 1)
    if repeat == 1:
        return f"seed {result['seed']}"
    return f"{repeat} runs per point (seeds {result['seed']}-{result['seed'] + repeat - 1})"


def _errors(points: list[dict[str, Any]], name: str) -> list[list[float]] | None:
    """Error bars (below, above the mean) from each point's interval; None when no point has one."""
    below, above = [], []
    for p in points:
        agg = (p.get("ci95") or {}).get(name)
        mean = p[name]
        below.append(0.0 if agg is None or mean is None else max(0.0, mean - agg["ci95_low"]))
        above.append(0.0 if agg is None or mean is None else max(0.0, agg["ci95_high"] - mean))
    return [below, above] if any(below) or any(above) else None


def _plot(out: Path, points: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, (rtt_ax, rate_ax) = plt.subplots(1, 2, figsize=(10, 4))
    for load in sorted({p["bg_mbps"] for p in points}):
        mine = sorted((p for p in points if p["bg_mbps"] == load), key=lambda p: p["priority_weight"])
        weights = [p["priority_weight"] for p in mine]
        for ax, name in ((rtt_ax, "rtt_loaded_mean_ms"), (rate_ax, "uav_delivered_mbps")):
            ax.errorbar(
                weights,
                [p[name] for p in mine],
                yerr=_errors(mine, name),
                marker="o",
                capsize=3,
                label=f"background {load:g}",
            )
    rtt_ax.set(xscale="log", yscale="log", xlabel="priority weight", ylabel="C&C RTT mean under load (ms)")
    rate_ax.set(xscale="log", xlabel="priority weight", ylabel="drone delivered (Mbit/s)")
    for ax in (rtt_ax, rate_ax):
        ax.set_xticks([p["priority_weight"] for p in points], [f"{p['priority_weight']:g}" for p in points])
        ax.xaxis.set_minor_formatter(NullFormatter())  # the weights are the ticks; no "3x10^0" between
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "sensitivity.png", dpi=100)
    plt.close(fig)
