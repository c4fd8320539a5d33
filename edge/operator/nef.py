"""3GPP NEF AsSessionWithQoS (TS 29.122 V18.4.0, API 3gpp-as-session-with-qos 1.3.0-alpha.4) over the
operator client: what a private or campus 5G core (OAI's NEF, a vendor's) offers where a public operator
offers CAMARA Quality-on-Demand.

A subscription asks the 5G core for the QoS named by `qosReference` on the UE's flows that `flowInfo`
describes (IPFilterRules, TS 29.214 clause 5.3.8: `permit out <proto> from <src> [<port>] to <dst>
[<port>]`, one for each direction). It lives until deleted (no duration to extend: `qosDuration`, when
given, bounds it); the NEF tells `notificationDestination` what happens to it (`UserPlaneNotificationData`)
and, when asked for QoS monitoring (TS 23.501 clause 5.33.3), the flow's measured delays.

Only the calls dynqos needs: create, read, modify (merge patch) and delete one subscription, and read
all of this SCS/AS's (to adopt or clean up after an agent that died). An answer without a subscription's
shape is a 502 BAD_RESPONSE, as for QoD: the agent never acts on half an answer.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import Any

from dynqos.edge.operator.client import OperatorClient, OperatorError

API = "/3gpp-as-session-with-qos/v1"
TCP = 6  # zenoh's flows are TCP (the protocol number of an IPFilterRule)
# The events a subscription asks to hear (UserPlaneEvent): the QoS held or lost, the session gone, the
# resources allocated or not, and the monitoring reports.
EVENTS = (
    "QOS_GUARANTEED",
    "QOS_NOT_GUARANTEED",
    "SESSION_TERMINATION",
    "SUCCESSFUL_RESOURCES_ALLOCATION",
    "FAILED_RESOURCES_ALLOCATION",
)
MONITORING = "QOS_MONITORING"


@dataclass(frozen=True, slots=True)
class FlowRule:
    """One flow between the UE and the edge: the UE's address, the edge's address and port."""

    ue: str
    server: str
    server_port: int
    protocol: int = TCP

    def descriptions(self) -> list[str]:
        """The flow's two IPFilterRules, uplink then downlink (TS 29.214 5.3.8: `permit out`, the source
        first, the UE's port left open: a TCP client's port is ephemeral)."""
        ue, server = _address(self.ue), _address(self.server)
        return [
            f"permit out {self.protocol} from {ue} to {server} {self.server_port}",
            f"permit out {self.protocol} from {server} {self.server_port} to {ue}",
        ]


@dataclass(frozen=True, slots=True)
class Monitoring:
    """QoS monitoring of the flow's packet delays (QosMonitoringInformation): what to measure and the
    reporting period."""

    period_s: int
    params: tuple[str, ...] = ("UPLINK", "DOWNLINK", "ROUND_TRIP")

    def body(self) -> dict[str, Any]:
        return {"reqQosMonParams": list(self.params), "repFreqs": ["PERIODIC"], "repPeriod": self.period_s}


@dataclass(frozen=True, slots=True)
class SubscriptionRequest:
    """What the agent asks for a drone: its UE (an address, or a GPSI where the NEF knows UEs by it),
    its priority flows, the QoS reference and its fall-backs."""

    ue_ipv4: str = ""
    ue_ipv6: str = ""
    gpsi: str = ""
    flows: tuple[FlowRule, ...] = ()
    qos_reference: str = ""
    alt_qos_references: tuple[str, ...] = ()
    notification_destination: str = ""
    qos_duration_s: int = 0  # 0: not given
    monitoring: Monitoring | None = None
    supported_features: str = ""

    def body(self) -> dict[str, Any]:
        """The AsSessionWithQoSSubscription to create; ValueError when something it needs is missing."""
        if not self.notification_destination:
            raise ValueError("a subscription needs a notificationDestination")
        if not (self.ue_ipv4 or self.ue_ipv6 or self.gpsi):
            raise ValueError("a subscription names the UE by ueIpv4Addr, ueIpv6Addr or gpsi")
        if not self.flows or not self.qos_reference:
            raise ValueError("a subscription needs the flows and a qosReference")
        body: dict[str, Any] = {
            "notificationDestination": self.notification_destination,
            "flowInfo": [
                {"flowId": n, "flowDescriptions": flow.descriptions()} for n, flow in enumerate(self.flows, 1)
            ],
            "qosReference": self.qos_reference,
            "events": [*EVENTS, *([MONITORING] if self.monitoring else [])],
        }
        for key, value in (("ueIpv4Addr", self.ue_ipv4), ("ueIpv6Addr", self.ue_ipv6), ("gpsi", self.gpsi)):
            if value:
                body[key] = value
        if self.alt_qos_references:
            body["altQoSReferences"] = list(self.alt_qos_references)
        if self.qos_duration_s:
            body["qosDuration"] = self.qos_duration_s
        if self.monitoring is not None:
            body["qosMonInfo"] = self.monitoring.body()
        if self.supported_features:
            body["supportedFeatures"] = self.supported_features
        return body


@dataclass(frozen=True, slots=True)
class Subscription:
    """The fields of an AsSessionWithQoSSubscription the agent acts on; `raw` is the whole object."""

    subscription_id: str  # the last segment of `self`, the resource's URI
    qos_reference: str
    ue: str  # ueIpv4Addr, ueIpv6Addr or gpsi, whichever it names
    raw: dict[str, Any] = field(repr=False)

    @classmethod
    def parse(cls, body: Any) -> Subscription:
        if not isinstance(body, dict) or not isinstance(body.get("self"), str) or not body["self"].strip("/"):
            raise OperatorError(
                502, "BAD_RESPONSE", f"not a subscription with its self link: {str(body)[:200]}"
            )
        if not isinstance(body.get("notificationDestination"), str):
            raise OperatorError(502, "BAD_RESPONSE", "a subscription without its notificationDestination")
        ue = next((str(body[k]) for k in ("ueIpv4Addr", "ueIpv6Addr", "gpsi") if body.get(k)), "")
        return cls(body["self"].rstrip("/").rsplit("/", 1)[-1], str(body.get("qosReference", "")), ue, body)


@dataclass(frozen=True, slots=True)
class Report:
    """One event of a UserPlaneNotificationData, with the delays of its QoS monitoring reports (ms)."""

    subscription_id: str  # from the notification's `transaction`, the subscription's URI
    event: str
    uplink_ms: tuple[int, ...] = ()
    downlink_ms: tuple[int, ...] = ()
    round_trip_ms: tuple[int, ...] = ()


def reports(body: Any) -> list[Report]:
    """The events of a notification, each with its delays; ValueError for what is not one."""
    if not isinstance(body, dict) or not isinstance(body.get("transaction"), str):
        raise ValueError("not a UserPlaneNotificationData: no transaction")
    events = body.get("eventReports")
    if not isinstance(events, list) or not events:
        raise ValueError("not a UserPlaneNotificationData: no eventReports")
    subscription = body["transaction"].rstrip("/").rsplit("/", 1)[-1]
    out = []
    for report in events:
        if not isinstance(report, dict) or not isinstance(report.get("event"), str):
            raise ValueError("an event report without its event")
        delays: dict[str, list[int]] = {"ulDelays": [], "dlDelays": [], "rtDelays": []}
        for monitored in report.get("qosMonReports") or []:
            for key, found in delays.items():
                found += [int(d) for d in (monitored or {}).get(key) or [] if isinstance(d, int) and d >= 0]
        out.append(
            Report(
                subscription,
                report["event"],
                tuple(delays["ulDelays"]),
                tuple(delays["dlDelays"]),
                tuple(delays["rtDelays"]),
            )
        )
    return out


class NefApi:
    """AsSessionWithQoS subscriptions of one SCS/AS at one NEF, over an open OperatorClient."""

    def __init__(self, operator: OperatorClient, api_root: str, scs_as_id: str) -> None:
        if not scs_as_id or "/" in scs_as_id:
            raise ValueError(f"scsAsId {scs_as_id!r}: a non-empty path segment")
        self.operator = operator
        self.root = f"{api_root.rstrip('/')}{API}/{scs_as_id}"

    async def create(self, request: SubscriptionRequest) -> Subscription:
        body = await self.operator.request(
            "POST", "/subscriptions", request.body(), expect=(201,), root=self.root
        )
        return Subscription.parse(body)

    async def get(self, subscription_id: str) -> Subscription:
        path = f"/subscriptions/{subscription_id}"
        return Subscription.parse(
            await self.operator.request("GET", path, None, expect=(200,), root=self.root)
        )

    async def modify(self, subscription_id: str, changes: dict[str, Any]) -> Subscription:
        """A merge patch (AsSessionWithQoSSubscriptionPatch): the new qosReference, flows, monitoring."""
        path = f"/subscriptions/{subscription_id}"
        patch = "application/merge-patch+json"
        body = await self._call("PATCH", path, changes, expect=(200, 204), content_type=patch)
        return Subscription.parse(body) if body is not None else await self.get(subscription_id)

    async def delete(self, subscription_id: str) -> None:
        path = f"/subscriptions/{subscription_id}"
        await self._call("DELETE", path, None, expect=(204, 200))

    async def all(self) -> list[Subscription]:
        body = await self._call("GET", "/subscriptions", None, expect=(200,))
        if not isinstance(body, list):
            raise OperatorError(502, "BAD_RESPONSE", "reading the subscriptions did not answer an array")
        return [Subscription.parse(item) for item in body]

    async def _call(self, method: str, path: str, body: Any, **how: Any) -> Any:
        return await self.operator.request(method, path, body, root=self.root, **how)


def _address(host: str) -> str:
    """An IP address as an IPFilterRule writes it, or its keyword `assigned` (RFC 6733: the address the
    network gave the UE, for a UE known by GPSI); ValueError for a name (a rule takes no host names)."""
    if host == "assigned":
        return host
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        raise ValueError(f"{host!r} is not an IP address: a flow description takes addresses") from None
