"""Benchmark: what a drone's second path costs the drone, the edge and the uplink (docs/multipath.md).

Flies `single-homed` and `dual-homed` without their faults and without background load (a calm
circle: the cost of the second path itself, not of what it rides out), alternately, once per seed, every
process real. From each run: the CPU seconds of the onboard daemon, of the edge (every router, MPC,
planner, QoS agent and detector of every site; the cells are the network, not counted) over the
recorded flight alone (from offloading to the end: start-up and climb left out), divided by its length,
and the drone's bytes each cell's uplink delivered. The second path sends each State, status and QoS
request twice (the camera rides one path) and hears each State's answer four times (two sites, two
paths), so the drone's cost is in its second session and the duplicates it decodes and drops; the
edge's is a second site, about twice one by construction. Target: the onboard daemon on two paths takes
at most 1.5x its CPU on one (the camera, which rides one path, is most of its work), and every run is
ok.

Run: dynqos bench second_path (suite settings), or with its own options:
  python -m dynqos.bench.second_path [--seeds 3] [--duration 30] [--quick] [--out FILE]
"""

from __future__ import annotations

import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.bench.report import emit, flight_args, judged, pct, provenance
from dynqos.bench.suite import spread
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import builtin_scenario

MODES = ("single-homed", "dual-homed")
ONBOARD_TARGET = 1.5  # the onboard daemon's CPU on two paths over one
EDGE = ("router", "mpc", "planner", "qos", "detector")  # an edge site's processes (name, or name-b)


def _edge_cpu_s(cpu_s: dict[str, float]) -> float:
    return sum(seconds for name, seconds in cpu_s.items() if name.removesuffix("-b") in EDGE)


def one_run(mode: str, seed: int, duration_s: float, out: Path) -> dict[str, Any]:
    scenario = replace(builtin_scenario(mode), seed=seed, duration_s=duration_s, faults=(), bg_start_s=-1)
    started = time.monotonic()
    summary = run_scenario(scenario, out / f"{mode}-seed{seed}", progress=False)
    wall_s = time.monotonic() - started
    cpu_s: dict[str, float] = summary.get("cpu_s_flight", {})  # over the recorded flight alone
    cell_b = (summary.get("cells") or {}).get("b") or {}
    return {
        "mode": mode,
        "seed": seed,
        "ok": summary["ok"],
        "wall_s": round(wall_s, 2),
        "cpu_s": cpu_s,
        "onboard_core_share": cpu_s.get("onboard", 0.0) / duration_s,
        "edge_core_share": _edge_cpu_s(cpu_s) / duration_s,
        "uplink_mbps": {"a": summary.get("uav_delivered_mbps"), "b": cell_b.get("uav_delivered_mbps")},
        "duplicates": (summary.get("multipath") or {}).get("duplicates"),
        "busy_share": (summary.get("machine") or {}).get("busy_share"),
    }


def _mode_figures(runs: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "onboard_core_share": spread([r["onboard_core_share"] for r in runs]),
        "edge_core_share": spread([r["edge_core_share"] for r in runs]),
        "uplink_mbps_a": spread([r["uplink_mbps"]["a"] for r in runs]),
        "uplink_mbps_b": spread([r["uplink_mbps"]["b"] for r in runs]),
        "busy_share": spread([r["busy_share"] for r in runs]),
        "ok_runs": sum(bool(r["ok"]) for r in runs),
    }


def _ratio(result: dict[str, Any], figure: str) -> float | None:
    one, two = (result["modes"][m][figure]["median"] for m in MODES)
    return None if not one or two is None else two / one


def run(seeds: int, duration_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="dynqos-bench-") as tmp:
        runs = [one_run(mode, seed, duration_s, Path(tmp)) for seed in range(seeds) for mode in MODES]
    result: dict[str, Any] = {
        "benchmark": "second_path",
        **provenance(),
        "duration_s": duration_s,
        "runs": runs,
        "modes": {mode: _mode_figures([r for r in runs if r["mode"] == mode]) for mode in MODES},
    }
    result["onboard_ratio"] = _ratio(result, "onboard_core_share")
    result["edge_ratio"] = _ratio(result, "edge_core_share")
    return result


def verdict(result: dict[str, Any]) -> str:
    one, two = (result["modes"][m] for m in MODES)
    failed = sum(not r["ok"] for r in result["runs"])

    def median(figure: dict[str, float | None]) -> str:
        return pct(figure["median"])

    def times(ratio: float | None) -> str:
        return "-" if ratio is None else f"{ratio:.2f}x"

    ratio = result["onboard_ratio"]
    met = ratio is not None and ratio <= ONBOARD_TARGET and not failed
    text = (
        f"onboard {median(one['onboard_core_share'])} -> {median(two['onboard_core_share'])} of a core "
        f"({times(ratio)}), edge {median(one['edge_core_share'])} -> {median(two['edge_core_share'])} "
        f"({times(result['edge_ratio'])}) with a second path and site"
        + (f"; {failed} run(s) not ok" if failed else "")
        + f" (target: onboard at most {ONBOARD_TARGET:g}x, every run ok)"
    )
    return judged(met, text)


def markdown(result: dict[str, Any]) -> str:
    def mbps(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    rows = [
        "| mode | seed | ok | onboard, share of a core | edge, share of a core "
        "| drone's uplink on cell a / b (Mbit/s) | duplicates | machine busy |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        rows.append(
            f"| {r['mode']} | {r['seed']} | {r['ok']} | {pct(r['onboard_core_share'])} "
            f"| {pct(r['edge_core_share'])} | {mbps(r['uplink_mbps']['a'])} / {mbps(r['uplink_mbps']['b'])} "
            f"| {r['duplicates'] if r['duplicates'] is not None else '-'} | {pct(r['busy_share'])} |"
        )
    medians = {
        mode: {name: v["median"] for name, v in figures.items() if isinstance(v, dict)}
        for mode, figures in result["modes"].items()
    }
    ratios = f"two paths / one: onboard {result['onboard_ratio']}, edge {result['edge_ratio']}"
    return "\n".join(rows) + f"\n\nmedians: {medians}; {ratios}"


def main(argv: list[str] | None = None) -> int:
    seeds, duration_s, out = flight_args(__doc__, argv, seeds_from=0, duration_s=30.0, quick_s=6.0)
    result = run(seeds, duration_s)
    return emit(result, markdown(result), out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
