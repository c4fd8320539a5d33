"""The QoS agent's messages: a drone's request for its priority flow, the network's grant, and the
arbiter's decisions (docs/qos.md). Registered and coded in common/messages.py, as every message is."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dynqos.common import fields as f
from dynqos.common.message_base import COMMON, LATENCY_MS, RISK_LEVELS, Message
from dynqos.common.modes import Grant


@dataclass(frozen=True, slots=True, kw_only=True)
class QosRequest(Message):
    """The drone to the QoS agent: whether it wants its priority flow from the network now. Sent on every
    change and repeated every [qos] request_interval_s; the agent forgets a drone it no longer hears."""

    TYPE: ClassVar[str] = "QosRequest"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "want": f.boolean,
        "risk": f.choice(RISK_LEVELS),
        "latency_excess": f.real(-1.0, 1.0),
        "offered_mbps": f.real(0.0, 1e5),
        "site": f.text(64),
    }

    stamp_ns: int
    want: bool
    # The drone's need, for an arbiter that cannot grant everyone (edge/qos/arbiter.py): its supervisor's
    # risk level, P_lat minus th_lat (0 while there is no latency evidence), and what it sends upward.
    risk: str = "NA"
    latency_excess: float = 0.0
    offered_mbps: float = 0.0
    # The edge site whose agent this request is for: a drone on two paths asks each site's agent (its own
    # operator) for its own path, and both agents hear both paths' requests (docs/multipath.md); "" = any
    site: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class QosDecision(Message):
    """The QoS agent's arbiter to everyone listening: one decision on one drone's priority, and why
    (`dynqos/<uav>/down/qos/decision`; tools subscribe to every drone's)."""

    TYPE: ClassVar[str] = "QosDecision"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "action": f.choice(("grant", "deny", "revoke", "release")),
        "reason": f.text(500),
        "risk": f.choice(RISK_LEVELS),
        "latency_excess": f.real(-1.0, 1.0),
        "holders": f.sequence(f.uav_id, max_len=1024),
    }

    stamp_ns: int
    action: str
    reason: str
    risk: str  # the drone's need as the arbiter saw it
    latency_excess: float
    holders: tuple[str, ...]  # who holds priority after this decision


@dataclass(frozen=True, slots=True, kw_only=True)
class QosGrant(Message):
    """The QoS agent to the drone: what the network grants its priority flow, and why."""

    TYPE: ClassVar[str] = "QosGrant"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "grant": f.member(Grant),
        "backend": f.choice(("links", "camara", "nef")),
        "session_id": f.text(64),
        "reason": f.text(300),
        "answers_seq": f.integer(),
        "site": f.text(64),
    }

    grant: Grant
    backend: str
    session_id: str = ""  # the QoD session ("" with the links backend or when there is none)
    reason: str = ""  # why the grant is what it is (the API's code and message on a refusal)
    answers_seq: int = 0  # the newest QosRequest seq the agent had when it sent this
    site: str = ""  # the site of the agent that says it ("" = one site): a drone on two paths hears two


@dataclass(frozen=True, slots=True, kw_only=True)
class QosMonitoring(Message):
    """The QoS agent to the drone: the 5G core's own measurement of the priority flow's packet delays
    (a NEF QOS_MONITORING report, TS 23.501 clause 5.33.3), forwarded as it arrives (docs/qos.md). Each
    delay is the largest the report gives, in ms; None where the report has none."""

    TYPE: ClassVar[str] = "QosMonitoring"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "subscription_id": f.text(64),
        "uplink_ms": f.optional(LATENCY_MS),
        "downlink_ms": f.optional(LATENCY_MS),
        "round_trip_ms": f.optional(LATENCY_MS),
        "period_s": f.integer(1, 3600),
    }

    stamp_ns: int  # the agent's clock when the report arrived
    subscription_id: str
    uplink_ms: float | None = None
    downlink_ms: float | None = None
    round_trip_ms: float | None = None
    period_s: int = 1  # the reporting period asked for: a report older than two is stale
