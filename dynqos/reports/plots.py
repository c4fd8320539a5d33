"""A flight's two pictures: overview.png (top view, tracking error, latencies, throughput) and
supervisor.png (the PFSM's state over time). matplotlib is imported only when a run draws them."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from pathlib import Path
from typing import Any

from dynqos.common.modes import SupervisorState
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import Scenario
from dynqos.reports.measures import tracking_errors

RHO2_MS = 27  # the paper's C&C threshold, drawn on the latency panel


def plot_flight(folder: Path, scenario: Scenario, rec: Recording, bg_start_s: float | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def shade(ax: Any) -> None:
        if bg_start_s is not None:
            ax.axvspan(bg_start_s, scenario.duration_s, color="tab:red", alpha=0.08, label="background load")

    fig, axes = plt.subplots(2, 2, figsize=(12, 8))
    _top_view(axes[0][0], rec)
    _tracking(axes[0][1], rec)
    _latencies(axes[1][0], rec)
    _throughput(axes[1][1], rec, scenario.scale)
    for ax in (axes[0][1], axes[1][0], axes[1][1]):
        shade(ax)
    for ax in (axes[1][0], axes[1][1]):
        ax.legend(fontsize=8)
    fig.suptitle(f"{scenario.name}: {scenario.description}", fontsize=10)
    fig.tight_layout()
    fig.savefig(folder / "overview.png", dpi=90)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(12, 2.5))
    _states(ax, rec)
    shade(ax)
    ax.set(title=f"{scenario.name}: supervisor state", xlabel="t (s)")
    fig.tight_layout()
    fig.savefig(folder / "supervisor.png", dpi=90)
    plt.close(fig)


def _top_view(ax: Any, rec: Recording) -> None:
    t0 = rec.t0_ns
    xs = [s.pos_m[0] for _, s in rec.states if s.stamp_ns >= t0]
    ys = [s.pos_m[1] for _, s in rec.states if s.stamp_ns >= t0]
    ref_xy = [(r.pos_m[0][0], r.pos_m[0][1]) for r in rec.refs if r.stamp_ns >= t0]
    if ref_xy:
        ax.plot([p[1] for p in ref_xy], [p[0] for p in ref_xy], "k--", lw=1, label="reference")
    ax.plot(ys, xs, lw=1, label="drone")
    ax.set(title="top view (north up)", xlabel="east y (m)", ylabel="north x (m)", aspect="equal")
    ax.legend(loc="upper right", fontsize=8)


def _tracking(ax: Any, rec: Recording) -> None:
    errors = tracking_errors(rec)
    ax.plot([t for t, _ in errors], [e for _, e in errors], lw=1)
    ax.set(title="tracking error", xlabel="t (s)", ylabel="m")


def _latencies(ax: Any, rec: Recording) -> None:
    t0 = rec.t0_ns
    for label, field in (("C&C RTT", "rtt_ms"), ("camera latency", "camera_latency_ms")):
        points = [
            ((s.stamp_ns - t0) / 1e9, v)
            for s in rec.status
            if (v := getattr(s, field)) is not None and s.stamp_ns >= t0
        ]
        ax.plot([t for t, _ in points], [v for _, v in points], lw=1, label=label)
    ax.axhline(RHO2_MS, color="gray", ls=":", lw=1, label=f"rho2 = {RHO2_MS} ms")
    ax.set(title="latency", xlabel="t (s)", ylabel="ms", yscale="log")


def _throughput(ax: Any, rec: Recording, scale: float) -> None:
    t0 = rec.t0_ns
    rows = [c for c in rec.cell if c["now_ns"] >= t0]
    picks: list[tuple[str, Callable[[dict[str, Any]], float]]] = [
        ("drone delivered", lambda c: sum(b["delivered_bytes"] * 8 for b in c["bearers"].values())),
        ("background delivered", lambda c: sum(b["delivered_bits"] for b in c["background"].values())),
    ]
    for label, pick in picks:
        series: list[tuple[float, float]] = []
        for a, b in itertools.pairwise(rows):
            span = (b["now_ns"] - a["now_ns"]) / 1e9
            series.append(((b["now_ns"] - t0) / 1e9, (pick(b) - pick(a)) / span / 1e6 * scale))
        ax.plot([t for t, _ in series], [v for _, v in series], lw=1, label=label)
    ax.set(title=f"throughput (Mbit/s at full scale; run at 1/{scale:g})", xlabel="t (s)", ylabel="Mbit/s")


def _states(ax: Any, rec: Recording) -> None:
    order = [s.value for s in SupervisorState]
    points = [
        ((s.stamp_ns - rec.t0_ns) / 1e9, order.index(s.state))
        for s in sorted(rec.status, key=lambda s: s.stamp_ns)
        if s.stamp_ns >= rec.t0_ns
    ]
    ax.step([t for t, _ in points], [v for _, v in points], where="post")
    ax.set_yticks(range(len(order)), order)
