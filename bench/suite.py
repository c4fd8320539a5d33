"""`dynqos bench`: run the benchmarks, each against its floor and target, and collect the figures.

Each benchmark module has `main(argv)` (with `--quick` for smoke mode and `--out FILE` for its JSON)
and prints a one-line verdict. The suite runs the chosen ones (all by default), `--repeat` times each,
keeps every result in `bench-results.json` and the tables in `bench-results.md`, and prints one line
per benchmark: its verdict, and with repeats the median and spread of its headline figures.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import json
import statistics
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from dynqos.bench.report import provenance
from dynqos.common.errors import DynqosError

Headline = Callable[[dict[str, Any]], dict[str, float | None]]


def _cvxpy_speedup(result: dict[str, Any], horizon: int) -> float | None:
    cv = result["cvxpy"].get(str(horizon))
    step = next(s for s in result["steps"] if s["horizon"] == horizon)
    return cv["median_ms"] / step["step"]["median_ms"] if cv else None


def _get(value: dict[str, Any] | None, key: str) -> float | None:
    return None if value is None else value[key]


def _edge_scale(result: dict[str, Any], mode: str, processes: int, key: str) -> float | None:
    run = next((r for r in result["runs"] if (r["mode"], r["processes"]) == (mode, processes)), None)
    return None if run is None else run[key]


# name -> the figures that summarise it (the ones docs/benchmarks.md quotes with their spread)
HEADLINES: dict[str, Headline] = {
    "supervisor_step": lambda r: {"step_median_us": r["step"]["median_us"]},
    "mpc_step": lambda r: {
        "ratio_to_osqp_n20": r["steps"][0]["ratio_median"],
        "ratio_to_osqp_n40": r["steps"][1]["ratio_median"],
        "step_median_ms_n20": r["steps"][0]["step"]["median_ms"],
        "cvxpy_speedup_n20": _cvxpy_speedup(r, 20),
        "drones_in_process": r["fleet"]["max_drones_at_20hz"],
    },
    "control_loop": lambda r: {
        "ours_p50_ms": r["ours"]["p50_ms"],
        "bare_p50_ms": r["bare_zenoh"]["p50_ms"],
        "mpc_p50_ms": r["mpc_in_process"]["p50_ms"],
        "ratio_p50": r["ratio_p50"],
    },
    "observability": lambda r: {
        "overhead_p50": r["overhead_p50"]["watched"],
        "metrics_overhead_p50": r["overhead_p50"]["metrics"],
        "viewer_overhead_p50": r["overhead_p50"]["viewer"],
        "bare_p50_ms": r["bare"]["p50_ms"],
        "watched_p50_ms": r["watched"]["p50_ms"],
    },
    "fleet_zenoh": lambda r: {
        "drones_one_by_one": r["one_by_one"]["max_drones_at_20hz"],
        "drones_batched": r["batched"]["max_drones_at_20hz"],
        "drones_floor": r["floor"]["max_drones_at_20hz"],
        "batched_over_floor_cpu_at_50": r["batched_over_floor_cpu_at_50"],
    },
    "edge_scale": lambda r: {
        "drones_one": _edge_scale(r, "one", 1, "max_drones_at_20hz"),
        "drones_two_replicas": _edge_scale(r, "replicas", 2, "max_drones_at_20hz"),
        "mpc_cpu_two_replicas_over_one": _edge_scale(r, "replicas", 2, "mpc_cpu_per_drone_over_one"),
    },
    "edge_per_drone": lambda r: {
        "per_drone_core_share": r["per_drone_core_share"],
        "bare_osqp_core_share_per_drone": r["bare_osqp_core_share_per_drone"],
        "mpc_over_bare": r["mpc_over_bare"],
        "minimal_mpc_over_bare": r["minimal_mpc_over_bare"],
    },
    "camera_rate": lambda r: {
        "controller_mean_us": r["controller"]["mean_us"],
        "floor_mean_us": r["floor"]["mean_us"],
        "ratio_mean": r["ratio_mean"],
    },
    "onboard_camera": lambda r: {"encode_publish_core_share": r["encode_publish_core_share_at_30fps"]},
    "vehicle_sim": lambda r: {
        "lockstep_speed": r["lockstep"]["sim_s_per_wall_s"],
        "render_fps": r["camera"]["render"]["fps"],
    },
    "cell_forward": lambda r: {"emulator_core_share": r["emulator"]["cpu_share_of_one_core"]},
    "supervisor_reaction": lambda r: {
        "switch_median_s": _get(r["switch_s"], "median"),
        "recovery_median_s": _get(r["recovery_s"], "median"),
    },
    "fleet_flight": lambda r: {
        "busy_share_max": r["busy_share"]["max"],
        "cpu_s_total_median": r["cpu_s_total"]["median"],
    },
    "second_path": lambda r: {
        "onboard_ratio": r["onboard_ratio"],
        "edge_ratio": r["edge_ratio"],
        "onboard_core_share_two_paths": r["modes"]["dual-homed"]["onboard_core_share"]["median"],
        "edge_core_share_two_sites": r["modes"]["dual-homed"]["edge_core_share"]["median"],
    },
    "ros2_bridge": lambda r: {
        "loop_change_p50": r["control_loop"]["change_p50"],
        "loop_floor_change_p50": r["control_loop"]["floor_change_p50"],
        "pose_added_p50_ms": r["pose_latency"]["added_p50_ms"],
        "per_drone_core_share": r["cpu"]["per_drone_core_share"],
    },
}
NAMES = tuple(HEADLINES)
# a benchmark of an extra's role -> (the module it needs, the extra): skipped from the default set
# without it, refused by name
NEEDS_EXTRA = {"ros2_bridge": ("rosbags", "ros2"), "camera_rate": ("aiortc", "camera-rate")}


def _missing_extra(name: str) -> str | None:
    need = NEEDS_EXTRA.get(name)
    if need is None or importlib.util.find_spec(need[0]) is not None:
        return None
    return f"{name} needs the {need[1]} extra: pip install 'dynqos[{need[1]}]'"


def spread(values: list[float | None]) -> dict[str, float | None]:
    present = [v for v in values if v is not None]
    if not present:
        return {"median": None, "min": None, "max": None}
    return {"median": statistics.median(present), "min": min(present), "max": max(present)}


HEARTBEAT_S = 30.0  # a benchmark that runs longer says so this often


@contextlib.contextmanager
def _still_running(what: str) -> Iterator[None]:
    """Print `what` is still running every HEARTBEAT_S (to the real stdout: the benchmark's own output
    goes to its log file), so minutes of silence never look like a hang."""
    stdout = sys.stdout
    done = threading.Event()
    started = time.monotonic()

    def beat() -> None:
        while not done.wait(HEARTBEAT_S):
            stdout.write(f"bench: {what}: still running ({time.monotonic() - started:.0f} s)\n")
            stdout.flush()

    thread = threading.Thread(target=beat, name="bench-heartbeat", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join(timeout=1)


def run_suite(names: list[str], *, smoke: bool, repeat: int, out: Path) -> dict[str, Any]:
    unknown = [n for n in names if n not in HEADLINES]
    if unknown:
        raise DynqosError(f"unknown benchmark {', '.join(unknown)}; choose from {', '.join(NAMES)}")
    if not 1 <= repeat <= 20:
        raise DynqosError(f"--repeat must be in 1..20, got {repeat}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DynqosError(f"cannot create {out}: {exc.strerror}") from None
    missing = [text for name in names if (text := _missing_extra(name))]
    if missing:
        raise DynqosError("; ".join(missing))
    chosen = names or [name for name in NAMES if _missing_extra(name) is None]
    for name in NAMES:
        if not names and (text := _missing_extra(name)):
            print(f"bench: skipped {text}", flush=True)
    suite: dict[str, Any] = {"suite": "dynqos bench", **provenance(), "smoke": smoke, "repeat": repeat}
    suite["benchmarks"] = {}
    tables = [f"# dynqos bench ({suite['date']}, {suite['machine']}{', smoke' if smoke else ''})", ""]
    started = time.monotonic()
    for number, name in enumerate(chosen, start=1):
        module = importlib.import_module(f"dynqos.bench.{name}")
        runs, seconds = [], []
        for index in range(repeat):
            json_path = out / f"{name}.{index}.json"
            log_path = out / f"{name}.{index}.log"
            t0 = time.monotonic()
            what = f"{name} ({number}/{len(chosen)}{f', run {index + 1}/{repeat}' if repeat > 1 else ''})"
            print(f"bench: {what}: running, its output in {log_path}", flush=True)
            with _still_running(what), log_path.open("w") as log, contextlib.redirect_stdout(log):
                module.main([*(["--quick"] if smoke else []), "--out", str(json_path)])
            seconds.append(time.monotonic() - t0)
            runs.append(json.loads(json_path.read_text()))
            json_path.unlink()
        figures = [HEADLINES[name](r) for r in runs]
        headline = {key: spread([f[key] for f in figures]) for key in figures[0]}
        suite["benchmarks"][name] = {"seconds": seconds, "headline": headline, "runs": runs}
        verdict = runs[-1]["verdict"]
        print(f"{name}: {verdict} [{sum(seconds):.0f} s]", flush=True)
        if repeat > 1:
            print("  " + "; ".join(f"{k} {_fmt(v)}" for k, v in headline.items()), flush=True)
        tables += [f"## {name}", "", (out / f"{name}.{repeat - 1}.log").read_text().split("\n}\n", 1)[-1], ""]
    suite["seconds"] = time.monotonic() - started
    (out / "bench-results.json").write_text(json.dumps(suite, indent=2) + "\n")
    (out / "bench-results.md").write_text("\n".join(tables) + "\n")
    print(f"wrote {out / 'bench-results.json'} and bench-results.md in {suite['seconds']:.0f} s")
    return suite


def _fmt(value: dict[str, float | None]) -> str:
    if value["median"] is None:
        return "-"
    return f"{value['median']:.3g} ({value['min']:.3g}..{value['max']:.3g})"
