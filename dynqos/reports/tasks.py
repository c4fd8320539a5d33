"""What the drone's offloaded tasks did in a flight (docs/offload.md), from its statuses alone: each
task's round trip before and under the load, its misses and fallback time, and for each fault whether
the task fell back while it lasted and how soon the edge's answers applied again after it cleared.

The load's window ends where the first fault begins: a kill's missing answers are the fault's, not the
load's. Statuses are read as data (SupervisorStatus.tasks); nothing here flies."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from dynqos.common.messages import SupervisorStatus
from dynqos.reports.measures import stats

SETTLE_NS = 10_000_000_000  # after a fault cleared, how long a return to the edge is looked for


def task_figures(
    statuses: Sequence[SupervisorStatus],
    settle_ns: int,
    bg_ns: int | None,
    end_ns: int,
    faults: Sequence[tuple[str, int, int]],
) -> dict[str, Any]:
    """By task name: figures over the flight. `faults`: (kind, start_ns, end_ns) of each fault."""
    ordered = sorted(statuses, key=lambda s: s.stamp_ns)
    names = list(dict.fromkeys(t[0] for s in ordered for t in s.tasks))
    first_fault = min((start for _, start, _ in faults), default=end_ns + 1)
    out: dict[str, Any] = {}
    for name in names:
        rows = [(s.stamp_ns, t) for s in ordered for t in s.tasks if t[0] == name]
        samples = [(stamp, ms) for stamp, t in rows for ms in t[6]]
        baseline = stats([ms for t, ms in samples if settle_ns <= t < (bg_ns or end_ns + 1)])
        loaded = stats([ms for t, ms in samples if bg_ns is not None and bg_ns <= t < first_fault])
        last = rows[-1][1]
        out[name] = {
            "rtt_ms": {"baseline": baseline, "loaded": loaded if bg_ns is not None else None},
            "loaded_over_baseline": _ratio(loaded["mean"], baseline["mean"]) if bg_ns is not None else None,
            "requests": last[2],
            "applied": last[3],
            "misses": last[4],
            "fallback_s": round(last[5], 2),
            "mode_at_end": last[1],
            "faults": [_through(rows, kind, start, stop) for kind, start, stop in faults],
        }
    return out


def _through(
    rows: list[tuple[int, tuple[Any, ...]]], kind: str, start_ns: int, end_ns: int
) -> dict[str, Any]:
    """Whether the task flew its fallback while the fault lasted, and when its edge answers applied again."""
    during = [t for stamp, t in rows if start_ns <= stamp <= end_ns + 1_000_000_000]
    fell_back = any(t[1] == "fallback" for t in during)
    back = next(
        (stamp for stamp, t in rows if end_ns <= stamp <= end_ns + SETTLE_NS and t[1] == "edge"),
        None,
    )
    return {
        "kind": kind,
        "fallback": fell_back,
        "back_at_edge_after_clear_s": None
        if back is None or not fell_back
        else round((back - end_ns) / 1e9, 2),
    }


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else round(a / b, 3)


def task_lines(summary: dict[str, Any]) -> list[str]:
    """The report's line per task."""
    lines = []
    for name, t in (summary.get("tasks") or {}).items():
        base, loaded = t["rtt_ms"]["baseline"], t["rtt_ms"]["loaded"] or {}
        faults = "; ".join(
            f"{f['kind']}: fallback {f['fallback']}, "
            f"back at the edge after {_fmt(f['back_at_edge_after_clear_s'])} s"
            for f in t["faults"]
        )
        lines.append(
            f"- task {name}: RTT (ms) baseline mean {_fmt(base['mean'])}, "
            f"loaded mean {_fmt(loaded.get('mean'))} "
            f"({_fmt(t['loaded_over_baseline'], 2)}x); {t['applied']} of {t['requests']} answers applied, "
            f"{t['misses']} misses, fallback {t['fallback_s']} s" + (f"; {faults}" if faults else "")
        )
    return lines


def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"
