"""Supervisor statuses for tests: a quiet one (q1 on the default flow, flown by the edge, low latency
and risk, nothing measured), changed where a test needs it."""

from __future__ import annotations

from typing import Any

from dynqos.common.messages import SupervisorStatus

QUIET: dict[str, Any] = {
    "uav": "uav1", "seq": 1, "stamp_ns": 0, "state": "q1", "flow": "default", "camera_flow": "default",
    "camera_rate_factor": 1.0, "control_source": "edge", "latency": "LL", "risk": "LR", "watchdog": False,
    "t_cam_ms": None, "t_cc_ms": None, "spaciousness_m": None, "p_cam": 0.0, "p_cc": 0.0, "p_lat": 0.0,
    "p_cs": 0.0, "prev_state": "q1", "cause": "", "changed_ns": 0,
}  # fmt: skip


def status(**changes: Any) -> SupervisorStatus:
    """The quiet status with `changes`."""
    return SupervisorStatus(**{**QUIET, **changes})


def status_saying(stamp_ns: int, text: str, severity: int | None, uav: str = "uav1") -> SupervisorStatus:
    """A quiet status carrying what the drone's FC said."""
    return status(uav=uav, stamp_ns=stamp_ns, fc_text=text, fc_severity=severity)
