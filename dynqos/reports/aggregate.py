"""Repeated runs of one scenario as one figure each: its mean and 95% confidence interval over runs.

The paper averages its runs; a figure from one run says nothing of how much the next would differ.
Every number of the runs' summaries (RTT means and percentiles, rates, tracking errors, times in
states, the switch time...) is aggregated by its path in the summary, e.g. `rtt_ms.loaded.mean`:
mean, and the Student-t interval of the mean (n - 1 degrees of freedom). One run gives a zero-width
interval. Runs where a figure is missing (None, e.g. no switch) are left out of that figure's `n`.
Injected faults and network changes are aggregated by their place in the scenario's list (the same in
every run): `faults.0.rtt_ms_during.mean`; their flags become the fraction of runs where they held
(`faults.0.fallback_fraction`).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterator
from typing import Any

SKIP = {
    "seed",
    "duration_s",
    "scale",
    "settle_s",
    "bg_mbps",
    "states_recorded",  # settings, not figures
    "arbiter_max_grants",
    "bg_weight",
    "uav_mbps_each",
}


def _numbers(summary: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, float]]:
    for key, value in summary.items():
        path = f"{prefix}{key}"
        if isinstance(value, bool) or (key in SKIP and not prefix):
            continue
        if isinstance(value, (int, float)) and math.isfinite(value):
            yield path, float(value)
        elif isinstance(value, dict):
            yield from _numbers(value, f"{path}.")
        elif key == "faults" and not prefix and isinstance(value, list):
            for index, fault in enumerate(value):
                if isinstance(fault, dict):
                    yield from _numbers(fault, f"{path}.{index}.")
                    for flag in ("fallback", "recovered"):
                        if isinstance(fault.get(flag), bool):
                            yield f"{path}.{index}.{flag}_fraction", float(fault[flag])


def interval(values: list[float]) -> dict[str, float | int]:
    """Mean and 95% confidence interval of the mean of `values` (Student t)."""
    n = len(values)
    mean = statistics.fmean(values)
    if n < 2:
        return {"mean": mean, "ci95_low": mean, "ci95_high": mean, "n": n}
    from scipy import stats as scipy_stats  # here: loading it costs every `dynqos demo` a second at start

    half = float(scipy_stats.t.ppf(0.975, n - 1)) * statistics.stdev(values) / math.sqrt(n)
    return {"mean": mean, "ci95_low": mean - half, "ci95_high": mean + half, "n": n}


def aggregate(runs: list[dict[str, Any]]) -> dict[str, dict[str, float | int]]:
    """Every figure of the runs' summaries by its path: {"rtt_ms.loaded.mean": {mean, ci95_low, ...}}."""
    values: dict[str, list[float]] = {}
    for run in runs:
        for path, value in _numbers(run):
            values.setdefault(path, []).append(value)
    return {path: interval(vs) for path, vs in sorted(values.items())}


def repeated_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """A repeated scenario's summary.json: the first run's identity, every run, and the aggregate."""
    first = runs[0]
    return {
        "scenario": first["scenario"],
        "profile": first.get("profile", "dynqos"),
        "fleet": first.get("fleet", False),
        "description": first.get("description", ""),
        "qos": first.get("qos"),
        "mission": first.get("mission"),
        "duration_s": first.get("duration_s"),
        "scale": first.get("scale"),
        "bg_mbps": first.get("bg_mbps"),  # a setting, the same in every run
        "uplink_trace": first.get("uplink_trace"),
        "seeds": [run.get("seed") for run in runs],
        "runs": runs,
        "aggregate": aggregate(runs),
        "ok": all(run["ok"] for run in runs),
        "failure": "; ".join(f"seed {run.get('seed')}: {run['failure']}" for run in runs if run["failure"]),
    }
