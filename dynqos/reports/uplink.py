"""report.md's table for flights on a traced uplink (the trace-* scenarios, docs/camera.md): what the
camera got through a capacity that follows a real LTE drive, and what that cost the control loop."""

from __future__ import annotations

from typing import Any

from dynqos.reports.figures import figure

COLUMNS = (  # (heading, the summary's path, digits)
    ("uplink delivered (Mbit/s)", "uav_delivered_mbps", 1),
    ("trace capacity (Mbit/s)", "uplink_capacity_mbps", 1),
    ("share carried", "uplink_share", 2),
    ("camera latency p50 (ms)", "camera_latency_ms.baseline.p50", 0),
    ("camera latency p95 (ms)", "camera_latency_ms.baseline.p95", 0),
    ("C&C RTT p95 (ms)", "rtt_ms.baseline.p95", 0),
    ("fallback (s)", "radio.fallback_s", 1),
    ("frames acked (per s)", "camera_fps.baseline", 1),
    ("dropped at the UE buffer (Mbit/s)", "uav_dropped_mbps", 2),
)


def traced_lines(summaries: list[dict[str, Any]]) -> list[str]:
    """The table over the scenarios that flew on a trace; none when no scenario did."""
    traced = [s for s in summaries if _trace(s)]
    if not traced:
        return []
    return [
        "",
        "## The camera on a traced uplink",
        "",
        "The cell's uplink capacity replayed a Mahimahi LTE trace (docs/camera.md), with no background "
        "load; figures over the recorded flight after settling, rates at full scale. Uplink delivered: "
        "everything the drone sent that the cell delivered (the camera is most of it). Frames acked: "
        "camera frames (RGB and depth) the detector acknowledged per second.",
        "",
        "| scenario | trace | runs | " + " | ".join(c[0] for c in COLUMNS) + " | ok |",
        "|---|---|---|" + "---|" * len(COLUMNS) + "---|",
        *(_row(s) for s in traced),
    ]


def _trace(summary: dict[str, Any]) -> str | None:
    value = summary.get("uplink_trace")
    return value if isinstance(value, str) else None


def _row(s: dict[str, Any]) -> str:
    runs = str(len(s.get("runs", [s])))
    cells = [
        s["scenario"],
        _trace(s) or "-",
        runs,
        *(figure(s, path, d) for _, path, d in COLUMNS),
        str(s["ok"]),
    ]
    return "| " + " | ".join(cells) + " |"
