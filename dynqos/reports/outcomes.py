"""What each injected fault did to the drone, read from its status stream after the flight.

The outcome of each fault is measured from the drone's status stream (SupervisorStatus carries who
flies, since when, and the age of the last valid command then): how long after its last valid command
the fallback took over, the longest pause in setpoints to the flight controller, and how long after
the fault cleared control was back at the edge. dynqos/experiment/faults.py injects the faults.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import ControlSource
from dynqos.plan.faults import SETTLE_S, FaultWindow


def time_in_states(
    statuses: Sequence[SupervisorStatus],
    since_ns: int | None = None,
    field: str = "state",
    *,
    within: tuple[int, int] | None = None,
) -> dict[str, float]:
    """Seconds with each value of a status field (the supervisor state by default; `risk`, `flow`...):
    a status's value lasts until the next status. Only the spans that start at or after `since_ns` count
    (all of them when None); with `within` (lo, hi), only the part of each span inside [lo, hi)."""
    out: dict[str, float] = {}
    lo, hi = within or (-math.inf, math.inf)
    for a, b in itertools.pairwise(statuses):
        if since_ns is None or a.stamp_ns >= since_ns:
            value = getattr(a, field)
            key = str(getattr(value, "value", value))
            span = max(0, min(b.stamp_ns, hi) - max(a.stamp_ns, lo))
            out[key] = out.get(key, 0.0) + span / NS_PER_S
    return out


def _while_it_lasted(during: list[SupervisorStatus], start_ns: int) -> dict[str, Any]:
    """What the drone saw and did while the fault lasted: its RTT, its time in each state, and how soon
    its camera was slowed (the rate-adaptation states, q4-q6) after the fault began."""
    rtts = sorted(v for s in during for v in s.rtt_samples_ms)
    states = time_in_states(during)
    slowed = next((s for s in during if s.camera_rate_factor < 1.0), None)
    rtt = None
    if rtts:
        rtt = {"mean": sum(rtts) / len(rtts), "p95": rtts[min(len(rtts) - 1, int(0.95 * len(rtts)))]}
    return {
        "rtt_ms_during": rtt,
        "states_s_during": {k: round(v, 2) for k, v in sorted(states.items())},
        "camera_slowed_after_s": None
        if slowed is None
        else round((slowed.stamp_ns - start_ns) / NS_PER_S, 2),
    }


def _signals(status: SupervisorStatus) -> dict[str, Any]:
    """What the supervisor saw in its last status of the window: why a drone not yet back is not."""
    return {
        "state": status.state.value,
        "latency": status.latency,
        "t_cam_ms": status.t_cam_ms,
        "t_cc_ms": status.t_cc_ms,
        "p_cam": status.p_cam,
        "p_cc": status.p_cc,
        "risk": status.risk,
    }


def log_times(text: str) -> list[tuple[float, str]]:
    """(wall time, message) of each line of a dynqos log (`%(asctime)s LEVEL name: message`)."""
    out = []
    for line in text.splitlines():
        try:
            stamp = datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
        except ValueError:
            continue
        out.append((stamp, line[24:]))
    return out


def _in_fallback_at(status: Sequence[SupervisorStatus], stamp_ns: int) -> SupervisorStatus | None:
    """The drone's last status at or before `stamp_ns` when its fallback was flying it then, else None."""
    before = [s for s in status if s.stamp_ns <= stamp_ns]
    last = max(before, key=lambda s: s.stamp_ns, default=None)
    return last if last is not None and last.control_source is ControlSource.FALLBACK else None


def outcome(
    window: FaultWindow,
    onboard_log: list[tuple[float, str]],
    status: Sequence[SupervisorStatus],
    next_start_ns: int | None,
    tracking_errors: Sequence[tuple[int, float]] = (),
) -> dict[str, Any]:
    """What the fault did, measured from the drone's SupervisorStatus stream: whether control fell back,
    how long after the last valid command, the longest setpoint gap, and when control was back at the
    edge; and from `tracking_errors` ((state stamp, distance to the published reference)) how far the
    drone left its mission. Its window runs from its start to SETTLE_S after it cleared, or to the next
    fault's start. The onboard log only supplies the lines a reader will want to see beside the figures."""
    fault = window.fault
    end_ns = window.end_ns if window.end_ns is not None else window.start_ns + to_ns(fault.duration_s)
    until_ns = end_ns + to_ns(SETTLE_S)
    if next_start_ns is not None:
        until_ns = min(until_ns, next_start_ns)
    seen = sorted((s for s in status if window.start_ns <= s.stamp_ns <= until_ns), key=lambda s: s.stamp_ns)
    at_start = _in_fallback_at(status, window.start_ns)
    fallback = at_start or next(
        (
            s
            for s in seen
            if s.control_source is ControlSource.FALLBACK
            and window.start_ns <= s.control_changed_ns <= end_ns + NS_PER_S
        ),
        None,
    )
    entered = None if at_start else fallback  # fell back in this fault's window, and when
    back = None
    if fallback is not None:
        since = fallback.control_changed_ns
        edge = (s for s in seen if s.control_source is ControlSource.EDGE and s.control_changed_ns > since)
        back = next(edge, None)
    gaps = [s.setpoint_gap_ms for s in seen if s.setpoint_gap_ms is not None]
    errors = [e for t, e in tracking_errors if window.start_ns <= t <= until_ns]
    during = [s for s in seen if s.stamp_ns <= end_ns]
    until_wall = window.start_wall + (until_ns - window.start_ns) / NS_PER_S
    lines = [m for t, m in onboard_log if window.start_wall <= t <= until_wall]
    notable = [m.split(": ", 1)[-1] for m in lines if m.startswith(("WARNING ", "ERROR "))]
    notable += [m.split(": ", 1)[-1] for m in lines if "control from the edge" in m][:1]
    return {
        "kind": fault.kind,
        "at_s": fault.at_s,
        "duration_s": fault.duration_s,
        # flown by its fallback while the fault lasted: fell back in it, or was there when it began (an
        # earlier fault's fallback not yet handed back); the two timings are for a fallback it caused
        "fallback": fallback is not None,
        "fallback_at_start": at_start is not None,
        "fallback_after_last_command_ms": None if entered is None else entered.command_age_ms,
        "fallback_after_fault_s": (
            None if entered is None else round((entered.control_changed_ns - window.start_ns) / NS_PER_S, 3)
        ),
        "max_setpoint_gap_ms": max(gaps) if gaps else None,
        "max_tracking_error_m": max(errors) if errors else None,
        # None: never left the edge (no fallback), or not back within `settle` (see "recovered")
        "back_at_edge_after_clear_s": (
            None if back is None else round(max(0.0, (back.control_changed_ns - end_ns) / NS_PER_S), 3)
        ),
        "recovered": fallback is None or back is not None,
        "at_window_end": _signals(seen[-1]) if seen else None,
        **_while_it_lasted(during, window.start_ns),
        "log": notable[:4],
        "notes": window.notes,
        **({"grant": window.grant} if window.grant is not None else {}),
    }
