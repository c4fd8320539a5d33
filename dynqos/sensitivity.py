"""`dynqos sensitivity`: where relative priority stops protecting the drone.

The paper's priority is relative: the priority bearer's scheduling weight against 1 for everyone else
(4 here), not a guaranteed rate. This flies `bg-staticqos` (the priority flow all along, so the
supervisor plays no part) once per priority weight and background load, and reports the drone's loaded
C&C RTT and delivered rate for each: a table, summary.json and sensitivity.png. With a weight w the
priority bearer's share of a full cell is w / (w + 1); once that share is below what the drone offers,
its queue grows as on the default flow.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.errors import ConfigError
from dynqos.figures import fmt
from dynqos.runner import run_scenario
from dynqos.scenario import builtin_scenario

log = logging.getLogger(__name__)

WEIGHTS = (1.0, 2.0, 4.0, 8.0)
LOADS_MBPS = (40.0, 80.0, 120.0)
MAX_POINTS = 64


def run_sensitivity(
    out: Path,
    *,
    weights: tuple[float, ...] = WEIGHTS,
    loads_mbps: tuple[float, ...] = LOADS_MBPS,
    duration_s: float = 20.0,
    seed: int = 0,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    if not weights or not loads_mbps or len(weights) * len(loads_mbps) > MAX_POINTS:
        raise ConfigError("--weights", f"give 1..{MAX_POINTS} (weight, load) points")
    stop = stop or threading.Event()
    base = builtin_scenario("bg-staticqos")
    points = []
    started = time.monotonic()
    for load in loads_mbps:
        for weight in weights:
            if stop.is_set():
                break
            scenario = replace(base, name=f"w{weight:g}-bg{load:g}", priority_weight=weight, bg_mbps=load,
                               duration_s=duration_s, bg_start_s=duration_s / 2, seed=seed)  # fmt: skip
            log.info("sensitivity: priority weight %g, background %g Mbit/s", weight, load)
            points.append(_point(weight, load, run_scenario(scenario, out, stop=stop, progress=False)))
    result = {
        "study": "sensitivity",
        "scenario": base.name,
        "duration_s": duration_s,
        "seed": seed,
        "scale": base.scale,
        "points": points,
        "wall_time_s": time.monotonic() - started,
        "ok": bool(points) and all(p["ok"] for p in points),
    }
    (out / "summary.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / "sensitivity.md").write_text(markdown(result))
    _plot(out, points)
    return result


def _point(weight: float, load: float, summary: dict[str, Any]) -> dict[str, Any]:
    loaded = summary["rtt_ms"]["loaded"] or {}
    return {
        "priority_weight": weight,
        "bg_mbps": load,
        "share_of_full_cell": weight / (weight + 1),
        "rtt_baseline_mean_ms": summary["rtt_ms"]["baseline"]["mean"],
        "rtt_loaded_mean_ms": loaded.get("mean"),
        "rtt_loaded_p95_ms": loaded.get("p95"),
        "uav_offered_mbps": summary["uav_offered_mbps"],
        "uav_admitted_mbps": summary["uav_admitted_mbps"],
        "uav_delivered_mbps": summary["uav_delivered_mbps"],
        "bg_delivered_mbps": summary["bg_delivered_mbps"],
        "ok": summary["ok"],
    }


def markdown(result: dict[str, Any]) -> str:
    lines = [
        "# Sensitivity: priority weight and background load",
        "",
        f"`{result['scenario']}` (the priority flow all along), {result['duration_s']:g} s per point with "
        f"the load from half-way, seed {result['seed']}, scale {result['scale']:g}. Rates at full scale.",
        "",
        "| priority weight | share of a full cell | background (Mbit/s) | RTT before / under load (ms) "
        "| RTT p95 under load (ms) | UAV offered / delivered (Mbit/s) | background delivered (Mbit/s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in result["points"]:
        lines.append(
            f"| {p['priority_weight']:g} | {p['share_of_full_cell']:.2f} | {p['bg_mbps']:g} "
            f"| {fmt(p['rtt_baseline_mean_ms'])} / {fmt(p['rtt_loaded_mean_ms'])} "
            f"| {fmt(p['rtt_loaded_p95_ms'])} "
            f"| {fmt(p['uav_offered_mbps'])} / {fmt(p['uav_delivered_mbps'])} "
            f"| {fmt(p['bg_delivered_mbps'])} |"
        )
    lines += ["", "![sensitivity](sensitivity.png)", ""]
    return "\n".join(lines)


def _plot(out: Path, points: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (rtt_ax, rate_ax) = plt.subplots(1, 2, figsize=(10, 4))
    for load in sorted({p["bg_mbps"] for p in points}):
        mine = sorted((p for p in points if p["bg_mbps"] == load), key=lambda p: p["priority_weight"])
        weights = [p["priority_weight"] for p in mine]
        rtt_ax.plot(
            weights, [p["rtt_loaded_mean_ms"] for p in mine], marker="o", label=f"background {load:g}"
        )
        rate_ax.plot(
            weights, [p["uav_delivered_mbps"] for p in mine], marker="o", label=f"background {load:g}"
        )
    rtt_ax.set(xscale="log", yscale="log", xlabel="priority weight", ylabel="C&C RTT mean under load (ms)")
    rate_ax.set(xscale="log", xlabel="priority weight", ylabel="drone delivered (Mbit/s)")
    for ax in (rtt_ax, rate_ax):
        ax.set_xticks([p["priority_weight"] for p in points], [f"{p['priority_weight']:g}" for p in points])
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "sensitivity.png", dpi=100)
    plt.close(fig)
