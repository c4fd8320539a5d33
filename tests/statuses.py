"""Supervisor statuses for tests that only need what one field of them says."""

from __future__ import annotations

from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import ControlSource, Flow, SupervisorState


def status_saying(stamp_ns: int, text: str, severity: int | None, uav: str = "uav1") -> SupervisorStatus:
    """A drone's status in q1 on the default flow, flown by the edge, carrying what its FC said."""
    q1 = SupervisorState.Q1
    return SupervisorStatus(
        uav=uav,
        seq=1,
        stamp_ns=stamp_ns,
        state=q1,
        flow=Flow.DEFAULT,
        camera_rate_factor=1.0,
        control_source=ControlSource.EDGE,
        camera_flow=Flow.DEFAULT,
        latency="LL",
        risk="LR",
        watchdog=False,
        t_cam_ms=None,
        t_cc_ms=None,
        spaciousness_m=None,
        p_cam=0.0,
        p_cc=0.0,
        p_lat=0.0,
        p_cs=0.0,
        prev_state=q1,
        cause="",
        changed_ns=0,
        fc_text=text,
        fc_severity=severity,
    )
