"""A figure by its path in a summary, as report.md and the command line print it: one run's value, or a
repeated scenario's mean and 95% interval over its runs (dynqos/reports/aggregate.py)."""

from __future__ import annotations

from typing import Any


def fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def lookup(summary: dict[str, Any], path: str) -> Any:
    """The value at a dotted path; a number indexes a list (`faults.0.fallback`); None where missing."""
    value: Any = summary
    for part in path.split("."):
        if isinstance(value, list) and part.isdigit():
            value = value[int(part)] if int(part) < len(value) else None
        elif isinstance(value, dict):
            value = value.get(part)
        else:
            return None
    return value


def mean_of(summary: dict[str, Any], path: str) -> float | None:
    if "aggregate" in summary:
        agg = summary["aggregate"].get(path)
        return None if agg is None else float(agg["mean"])
    value = lookup(summary, path)
    return float(value) if isinstance(value, (int, float)) else None


def figure(summary: dict[str, Any], path: str, digits: int = 1) -> str:
    """A figure by its path in a summary: the value of one run, or "mean [low, high]" over repeated runs."""
    if "aggregate" not in summary:
        value = lookup(summary, path)
        return fmt(value if isinstance(value, (int, float)) else None, digits)
    agg = summary["aggregate"].get(path)
    return "-" if agg is None else interval_text(agg, digits)


def interval_text(agg: dict[str, Any], digits: int = 1) -> str:
    """An aggregated figure ({mean, ci95_low, ci95_high, n}) as "mean [low, high]" (one run: the mean)."""
    if agg["n"] < 2:
        return fmt(agg["mean"], digits)
    return f"{agg['mean']:.{digits}f} [{agg['ci95_low']:.{digits}f}, {agg['ci95_high']:.{digits}f}]"
