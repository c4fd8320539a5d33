"""The QoS agent's health line (edge/qos/agent.py): its drones and sessions, its calls to the operator,
the arbiter's decisions, the notifications its sink took, and which agent of its site is active."""

from __future__ import annotations

from typing import TYPE_CHECKING

from dynqos.edge.qos.arbiter import Action
from dynqos.edge.qos.nef_calls import NefCalls

if TYPE_CHECKING:
    from dynqos.edge.qos.agent import QosAgent


def health_line(agent: QosAgent) -> str:
    sessions = sum(r.grant.session is not None for r in agent.drones.values())
    lead = agent.leadership
    site = f" site={agent.qos.site}" if agent.qos.site else ""
    role = f" agent={lead.me}{site} role={lead.role.value} agents={len(lead.members)}"
    calls = f" api_calls={agent.client.calls} retries={agent.client.retries}" if agent.client else ""
    arbiter = ""
    if agent.arbiter is not None:
        d = agent.decisions
        arbiter = (
            f" holders={len(agent.arbiter.holders)} grants={d[Action.GRANT]} denials={d[Action.DENY]} "
            f"revocations={d[Action.REVOKE]} releases={d[Action.RELEASE]}"
        )
    sink, nef = "", agent.qos.backend == "nef"
    if nef or agent.camara.sink_listen:
        c = agent.nef_guard.counters if nef else agent.sink_guard.counters
        sink = f" notifications={c['taken']} refused={c['unauthenticated'] + c['malformed']}"
        sink += f" monitoring_reports={agent.calls.reports}" if isinstance(agent.calls, NefCalls) else ""
        sink += "" if nef else f" replayed={c['replayed']}"
    return (
        f"drones={len(agent.drones)} sessions={sessions} errors={agent.errors} "
        f"leftovers_cleaned={agent.cleaned}{calls}{arbiter}{sink} rejected={agent.stats.rejected}{role} "
        f"takeovers={lead.takeovers}"
    )
