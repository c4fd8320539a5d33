"""Benchmark: how much of this machine a four-drone fleet takes, and what its drones' baseline RTT is.

Runs the `fleet-arbiter` scenario (four drones in one emulated cell, every process real) once per seed
and reads what the flight recorded of the machine: the busy share of all cores over the recorded
flight, its busiest second, the seconds above 85% (dynqos/experiment/machine.py: a run with more than
3 is starved), the CPU seconds of every process, and each drone's baseline RTT (before the load).
Target: at most 70% busy and never starved in every run, so that the fleet's figures are the
network's and not the CPU's (docs/fleet.md). The fleet's scenario tests assert behaviour; how busy it
keeps a machine is this benchmark's figure, since the same code costs more on a slower host.

Run: dynqos bench fleet_flight (suite settings), or with its own options:
  python -m dynqos.bench.fleet_flight [--seeds 3] [--duration 45] [--quick] [--out FILE]
"""

from __future__ import annotations

import json
import statistics
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.bench.report import emit, flight_args, judged, pct, provenance
from dynqos.bench.suite import spread
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import builtin_scenario

BUSY_TARGET = 0.70


def one_run(seed: int, duration_s: float, out: Path) -> dict[str, Any]:
    base = builtin_scenario("fleet-arbiter")
    bg_start_s = base.bg_start_s if duration_s >= base.bg_start_s + 10 else duration_s / 2
    scenario = replace(base, seed=seed, duration_s=duration_s, bg_start_s=bg_start_s)
    summary = run_scenario(scenario, out / f"seed{seed}", progress=False)
    machine = summary.get("machine") or {}
    means = [(d["rtt_ms"].get("baseline") or {}).get("mean") for d in summary["drones"].values()]
    baselines = [m for m in means if m is not None]  # a short flight may have no baseline window
    return {
        "seed": seed,
        "ok": summary["ok"],
        "busy_share": machine.get("busy_share"),
        "busy_share_max_1s": machine.get("busy_share_max_1s"),
        "seconds_above_85": machine.get("seconds_above_85"),
        "starved": machine.get("starved"),
        "cpu_s": summary.get("cpu_s", {}),
        "cpu_s_total": round(sum(summary.get("cpu_s", {}).values()), 2),
        "baseline_rtt_mean_ms": statistics.fmean(baselines) if baselines else None,
    }


def run(seeds: int, duration_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="dynqos-bench-") as tmp:
        runs = [one_run(seed, duration_s, Path(tmp)) for seed in range(seeds)]
    busy = [r["busy_share"] for r in runs]
    return {
        "benchmark": "fleet_flight",
        **provenance(),
        "duration_s": duration_s,
        "runs": runs,
        "busy_share": spread(busy),
        "cpu_s_total": spread([r["cpu_s_total"] for r in runs]),
        "baseline_rtt_mean_ms": spread([r["baseline_rtt_mean_ms"] for r in runs]),
        "starved_runs": sum(bool(r["starved"]) for r in runs),
    }


def verdict(result: dict[str, Any]) -> str:
    busy = result["busy_share"]
    runs = len(result["runs"])
    met = busy["max"] is not None and busy["max"] <= BUSY_TARGET and result["starved_runs"] == 0
    text = (
        "no machine figures"
        if busy["max"] is None
        else (
            f"busy {100 * busy['min']:.0f}-{100 * busy['max']:.0f}% over {runs} run(s), "
            f"{result['starved_runs']} starved, CPU {result['cpu_s_total']['median']:.0f} s per run "
            f"(target: at most {100 * BUSY_TARGET:.0f}% busy and none starved)"
        )
    )
    return judged(met, text)


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| seed | busy over the flight | busiest second | s above 85% | starved | CPU s (all processes) "
        "| baseline RTT mean (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        rtt = r["baseline_rtt_mean_ms"]
        rows.append(
            f"| {r['seed']} | {pct(r['busy_share'])} | {pct(r['busy_share_max_1s'])} "
            f"| {r['seconds_above_85']} | {r['starved']} | {r['cpu_s_total']} "
            f"| {'-' if rtt is None else f'{rtt:.1f}'} |"
        )
    return "\n".join(rows) + "\n\n" + json.dumps({"busy_share": result["busy_share"]})


def main(argv: list[str] | None = None) -> int:
    seeds, duration_s, out = flight_args(__doc__, argv, seeds_from=0, duration_s=45.0, quick_s=8.0)
    result = run(seeds, duration_s)
    return emit(result, markdown(result), out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
