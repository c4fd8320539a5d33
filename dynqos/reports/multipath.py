"""A drone on two paths (docs/multipath.md): its figures in the summary and its rows in report.md.

Every figure comes from the drone's statuses: each path's command RTTs (the first answer to each
State copy it carried, down either path: its uplink), the winner's (the Commands applied: the drone's own
`rtt_ms`), the Commands each site won, the duplicates dropped, the camera's path over time and how
long each path's own PFSM kept its traffic on the priority flow.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import Flow
from dynqos.common.stats import percentile
from dynqos.plan.faults import SETTLE_S, SITE_FAULTS, FaultWindow
from dynqos.reports.figures import figure
from dynqos.reports.outcomes import time_in_states


def _spread(samples: Sequence[float]) -> dict[str, float] | None:
    if not samples:
        return None
    return {
        "n": len(samples),
        "p50": round(percentile(samples, 50), 2),
        "p95": round(percentile(samples, 95), 2),
        "p99": round(percentile(samples, 99), 2),
    }


Span = tuple[int, int]  # [from, to) in ns, the drone's clock


def _within(spans: Sequence[Span], stamp_ns: int) -> bool:
    return any(lo <= stamp_ns < hi for lo, hi in spans)


def fault_spans(windows: Sequence[FaultWindow]) -> tuple[list[Span], list[Span]]:
    """(the spans a cell carried background load, the spans a site or cell was out and SETTLE_S after)."""
    loaded = [(w.start_ns, w.end_ns or w.start_ns) for w in windows if w.fault.kind == "background"]
    out = [
        (w.start_ns, (w.end_ns or w.start_ns) + to_ns(SETTLE_S))
        for w in windows
        if w.fault.kind in SITE_FAULTS
    ]
    return loaded, out


def path_figures(
    statuses: Sequence[SupervisorStatus],
    t0_ns: int,
    loaded: Sequence[Span] = (),
    faulted: Sequence[Span] = (),
) -> dict[str, Any] | None:
    """The summary's `multipath` figures over the recorded flight. `loaded`: the spans a cell carried
    background load; `faulted`: the spans a site or a cell was out, and the settling after. The winner's
    RTT is given under load outside the faults (`rtt_ms_winner_loaded`) and in the faults
    (`rtt_ms_winner_faulted`) apart: a drone on one path has no answer at all while its site is down,
    and its RTT after is its reconnection's, not the load's. A drone on one path gets the winner's
    figures only (the same, for comparison)."""
    flown = [s for s in statuses if s.stamp_ns >= t0_ns]
    if not flown:
        return None
    paths: dict[str, list[float]] = {}
    for status in flown:
        for name, samples in status.path_rtt_samples_ms:
            paths.setdefault(name, []).extend(samples)
    first, last = flown[0], flown[-1]
    wins_before, wins = dict(first.site_wins), dict(last.site_wins)
    won = {site: n - wins_before.get(site, 0) for site, n in wins.items()}
    total = sum(won.values())
    camera = time_in_states(flown, field="camera_path")
    priority: dict[str, float] = {}  # each path's seconds on the priority flow, by its own PFSM
    for a, b in itertools.pairwise(flown):
        for name, _, flow in a.path_states:
            span = (b.stamp_ns - a.stamp_ns) / NS_PER_S if flow is Flow.PRIORITY else 0.0
            priority[name] = priority.get(name, 0.0) + span
    return {
        "rtt_ms_by_path": {name: _spread(samples) for name, samples in sorted(paths.items())},
        "rtt_ms_winner": _spread([v for s in flown for v in s.rtt_samples_ms]),
        "rtt_ms_winner_loaded": _spread(
            [
                v
                for s in flown
                if _within(loaded, s.stamp_ns) and not _within(faulted, s.stamp_ns)
                for v in s.rtt_samples_ms
            ]
        ),
        "rtt_ms_winner_faulted": _spread(
            [v for s in flown if _within(faulted, s.stamp_ns) for v in s.rtt_samples_ms]
        ),
        "commands_won": dict(sorted(won.items())),
        "share_won": {site: round(n / total, 3) for site, n in sorted(won.items())} if total else {},
        "duplicates": last.duplicates - first.duplicates,
        "camera_path_s": {k: round(v, 1) for k, v in sorted(camera.items())},
        "priority_s_by_path": {k: round(v, 1) for k, v in sorted(priority.items())},
    }


def _triple(s: dict[str, Any], path: str) -> str:
    return " / ".join(figure(s, f"{path}.{q}", 0) for q in ("p50", "p95", "p99"))


def _has_paths(summary: dict[str, Any]) -> bool:
    runs = summary.get("runs") or [summary]
    return isinstance(runs[0].get("multipath"), dict)


def multipath_lines(summaries: list[dict[str, Any]]) -> list[str]:
    """report.md's table over the scenarios with `multipath` figures (two paths, or a site or cell lost;
    one run or repeated, with intervals); none otherwise."""
    rows = [s for s in summaries if _has_paths(s)]
    if not rows:
        return []
    lines = [
        "",
        "## Two paths, two sites",
        "",
        "Command RTT p50 / p95 / p99 (ms) of the Commands applied (the winner's): over the flight, while "
        "a cell carried background load (outside the faults), and from a site kill or cell outage to "
        f"{SETTLE_S:g} s after it; and each path's own (the first answer to each State it carried). "
        "The share of applied "
        "Commands each site won; seconds each path's own PFSM kept it on the priority flow; duplicates "
        "dropped; seconds the fallback flew, as the drone counted them "
        "(docs/multipath.md).",
        "",
        "| scenario | runs | winner | under load | in a fault | path a | path b | won by site a / b "
        "| on priority, path a / b (s) | duplicates | fallback (s) | longest setpoint gap (ms) | ok |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in rows:
        cells = [
            s["scenario"],
            str(len(s.get("runs", [s]))),
            _triple(s, "multipath.rtt_ms_winner"),
            _triple(s, "multipath.rtt_ms_winner_loaded"),
            _triple(s, "multipath.rtt_ms_winner_faulted"),
            _triple(s, "multipath.rtt_ms_by_path.a"),
            _triple(s, "multipath.rtt_ms_by_path.b"),
            " / ".join(figure(s, f"multipath.share_won.{site}", 2) for site in ("a", "b")),
            " / ".join(figure(s, f"multipath.priority_s_by_path.{path}", 1) for path in ("a", "b")),
            figure(s, "multipath.duplicates", 0),
            figure(s, "fallback_flown_s", 1),
            figure(s, "setpoint_gap_max_ms", 0),
            str(s["ok"]),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines + _cell_lines(rows)


def _cell_lines(rows: list[dict[str, Any]]) -> list[str]:
    """What each cell's uplink carried: the drone's bytes delivered (the camera rides one path, States,
    statuses and QoS requests both) and the background user's, over the summary's `rates_span`."""
    lines = [
        "",
        "Each cell's uplink, Mbit/s at full scale (the summary's `rates_span`): the drone's bytes delivered "
        "and the background user's; cell b's are the second path's cost on the uplink.",
        "",
        "| scenario | runs | cell a: drone / background | cell b: drone / background |",
        "|---|---|---|---|",
    ]
    for s in rows:
        cells = [  # cell a's rates are the summary's own, cell b's under cells.b
            " / ".join(figure(s, f"{prefix}{name}_mbps", 1) for name in ("uav_delivered", "bg_delivered"))
            for prefix in ("", "cells.b.")
        ]
        lines.append(f"| {s['scenario']} | {len(s.get('runs', [s]))} | {' | '.join(cells)} |")
    return lines
