"""A supervisor decision as the SupervisorStatus the drone publishes: its state, signals, probabilities
and last transition. Kept apart from the PFSM (onboard/supervisor.py), which knows no message."""

from __future__ import annotations

from typing import Any

from dynqos.common.messages import SupervisorStatus
from dynqos.onboard.supervisor import Decision, Transition


def decision_fields(decision: Decision, last: Transition | None) -> dict[str, Any]:
    """The SupervisorStatus fields that describe a decision: state, signals, P values, last transition."""
    s = decision.signals
    return {
        "state": decision.state,
        "latency": s.latency.value,
        "risk": s.risk.value,
        "watchdog": s.watchdog,
        "t_cam_ms": s.t_cam_ms,
        "t_cc_ms": s.t_cc_ms,
        "spaciousness_m": s.spaciousness_m,
        "depth_lost": s.depth_lost,
        "p_cam": s.p_cam or 0.0,
        "p_cc": s.p_cc or 0.0,
        "p_lat": s.p_lat or 0.0,
        "p_cs": s.p_cs or 0.0,
        "prev_state": last.source if last else decision.state,
        "cause": (last.cause if last else "")[:200],
        "changed_ns": last.stamp_ns if last else 0,
    }


def to_status(
    decision: Decision, *, uav: str, seq: int, stamp_ns: int, last: Transition | None
) -> SupervisorStatus:
    """The status of a drone that does exactly what the decision's actions say."""
    a = decision.actions
    return SupervisorStatus(
        uav=uav,
        seq=seq,
        stamp_ns=stamp_ns,
        flow=a.flow,
        camera_flow=a.camera_flow,
        camera_rate_factor=a.camera_rate_factor,
        control_source=a.control_source,
        **decision_fields(decision, last),
    )
