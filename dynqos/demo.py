"""`dynqos demo` and `dynqos run FILE`: the paper's experiment, scenario after scenario, on one machine.

Each scenario runs as real processes (dynqos/runner.py); the demo applies the command line's overrides,
stops cleanly on Ctrl-C, and writes summary.json and the report over all scenarios (dynqos/report.py).
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
from dynqos.report import write_report
from dynqos.runner import run_scenario
from dynqos.scenario import Scenario, builtin_scenario

log = logging.getLogger(__name__)


def run_demo(
    names: list[str],
    out: Path,
    *,
    duration_s: float | None,
    scale: float | None,
    seed: int | None,
    scenarios: list[Scenario] | None = None,
) -> dict[str, Any]:
    chosen = scenarios if scenarios is not None else [builtin_scenario(n) for n in names]
    overrides: dict[str, Any] = {}
    if duration_s is not None:
        overrides["duration_s"] = duration_s
    if scale is not None:
        overrides["scale"] = scale
    if seed is not None:
        overrides["seed"] = seed
    runs = []
    for scenario in chosen:
        if overrides:
            changes = dict(overrides)
            if "duration_s" in changes and scenario.bg_start_s >= 0:
                changes["bg_start_s"] = changes["duration_s"] / 2
            try:
                scenario = replace(scenario, **changes)
            except ConfigError as exc:
                raise exc.under(scenario.name) from None
        runs.append(scenario)
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
    try:
        for scenario in runs:
            if stop.is_set():
                break
            log.info("scenario %s: %s", scenario.name, scenario.description)
            summary = run_scenario(scenario, out, stop=stop)
            summaries.append(summary)
            log.info(
                "scenario %s: ok=%s rtt baseline mean %s ms, loaded mean %s ms",
                scenario.name,
                summary["ok"],
                _fmt(summary["rtt_ms"]["baseline"]),
                _fmt(summary["rtt_ms"]["loaded"]),
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    top = {
        "scenarios": summaries,
        "wall_time_s": time.monotonic() - started,
        "out": str(out),
        "ok": bool(summaries) and all(s["ok"] for s in summaries) and len(summaries) == len(runs),
    }
    (out / "summary.json").write_text(json.dumps(top, indent=2) + "\n")
    write_report(out, summaries)
    return top


def _fmt(stats: dict[str, Any] | None) -> str:
    return "-" if not stats or stats.get("mean") is None else f"{stats['mean']:.1f}"


def default_out_dir() -> Path:
    return Path("runs") / time.strftime("%Y%m%d-%H%M%S")
