"""The measures a report computes from a recording: summary statistics, the distance between where the
drone was and where its reference said it should be, and their RMS."""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable

import numpy as np

from dynqos.common.messages import Reference, State
from dynqos.plan.recording import Recording


def stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"mean": None, "p50": None, "p95": None, "p99": None, "max": None, "n": 0}
    a = np.array(values)
    return {
        "mean": float(a.mean()),
        "p50": float(np.percentile(a, 50)),
        "p95": float(np.percentile(a, 95)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "n": len(values),
    }


def reference_errors(states: Iterable[State], references: Iterable[Reference]) -> list[tuple[int, float]]:
    """(stamp_ns, distance to the reference sample due at the state's stamp) for every state that a
    reference covers. Drone and planner stamps must share a clock: the same host, as in the demo."""
    refs = sorted(references, key=lambda r: r.stamp_ns)
    stamps = [r.stamp_ns for r in refs]
    out = []
    for s in states:
        i = bisect.bisect_right(stamps, s.stamp_ns) - 1
        if i < 0:
            continue
        ref = refs[i]
        k = (s.stamp_ns - ref.stamp_ns) / 1e9 / ref.dt_s
        lo = min(int(k), len(ref.pos_m) - 1)
        hi = min(lo + 1, len(ref.pos_m) - 1)
        f = k - int(k)
        target = np.array(ref.pos_m[lo]) * (1 - f) + np.array(ref.pos_m[hi]) * f
        out.append((s.stamp_ns, float(np.linalg.norm(np.array(s.pos_m) - target))))
    return out


def tracking_errors(rec: Recording) -> list[tuple[float, float]]:
    """(t_s since offloading started, tracking error) for every recorded state."""
    errors = reference_errors((s for _, s in rec.states), rec.refs)
    return [((stamp - rec.t0_ns) / 1e9, error) for stamp, error in errors]


def rmse(values: list[float]) -> float | None:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else None
