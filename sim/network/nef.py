"""The emulated 5G core's NEF: AsSessionWithQoS subscriptions (TS 29.122 V18.4.0) over the same cell as
the CAMARA operator, for a private or campus network whose core the edge asks directly. Pure logic with
the clocks passed in; sim/network/api_nef.py serves it.

A subscription names the UE (ueIpv4Addr, ueIpv6Addr or gpsi) and its flows as IPFilterRules (TS 29.214
clause 5.3.8); the edge end of each rule names the drone's edge host and a port. It is allocated after
[cell] qod_setup_s if the core admits it ([cell] qod_max_sessions, the same limit as QoD's), and from
then the drone's bearers to those ports get their priority weight until it is deleted or its
`qosDuration` runs out. The NEF tells `notificationDestination` what happened
(UserPlaneNotificationData: SUCCESSFUL_RESOURCES_ALLOCATION and QOS_GUARANTEED, or
FAILED_RESOURCES_ALLOCATION; SESSION_TERMINATION when the network ends it) and, with QoS monitoring
asked for, the flow's measured delays every `repPeriod` seconds (QOS_MONITORING).
"""

from __future__ import annotations

import ipaddress
import json
import re
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dynqos.common.config import CellConfig
from dynqos.sim.network.operator import Answer, Notification

API = "/3gpp-as-session-with-qos/v1"
MAX_SUBSCRIPTIONS = 10_000  # every SCS/AS together: a client that never deletes cannot grow this
JSON = "application/json"
IDENTITIES = ("ueIpv4Addr", "ueIpv6Addr", "gpsi")
# TS 29.571's patterns for MacAddr48 and for the three forms of an IpAddr (a read's query names UEs so)
MAC48 = re.compile(r"[0-9a-fA-F]{2}(-[0-9a-fA-F]{2}){5}")
_V6 = (
    r"((:|(0?|([1-9a-f][0-9a-f]{0,3}))):)((0?|([1-9a-f][0-9a-f]{0,3})):){0,6}(:|(0?|([1-9a-f][0-9a-f]{0,3})))"
)
_V6_SHAPE = r"((([^:]+:){7}([^:]+))|((([^:]+:)*[^:]+)?::(([^:]+:)*[^:]+)?))"
_PREFIX = r"(\/(([0-9])|([0-9]{2})|(1[0-1][0-9])|(12[0-8])))"
IP_ADDR = {
    "ipv4Addr": [
        re.compile(
            r"(([0-9]|[1-9][0-9]|1[0-9][0-9]|2[0-4][0-9]|25[0-5])\.){3}([0-9]|[1-9][0-9]|1[0-9][0-9]|2[0-4][0-9]|25[0-5])"
        )
    ],
    "ipv6Addr": [re.compile(_V6), re.compile(_V6_SHAPE)],
    "ipv6Prefix": [re.compile(_V6 + _PREFIX), re.compile(_V6_SHAPE + r"(\/.+)")],
}
# what a patch may change (AsSessionWithQoSSubscriptionPatch, the fields dynqos's emulation acts on)
PATCHABLE = {
    "flowInfo",
    "qosReference",
    "altQoSReferences",
    "qosDuration",
    "qosMonInfo",
    "events",
    "notificationDestination",  # a new active agent's sink
}
Delays = Callable[[str], tuple[int, int, int]]  # a drone's uplink, downlink and round-trip delay now (ms)


def problem(status: int, cause: str, detail: str) -> Answer:
    """A ProblemDetails (TS 29.122 clause 5.2.1.2.12)."""
    body = {"status": status, "cause": cause, "detail": detail, "title": cause}
    return Answer(status, body, content_type="application/problem+json")


@dataclass(frozen=True, slots=True)
class Rule:
    """The parts of an IPFilterRule this NEF acts on: the flow's two ends and the ports of each."""

    source: str
    source_ports: frozenset[int]
    destination: str
    destination_ports: frozenset[int]


def parse_rule(text: str) -> Rule:
    """`permit out <proto> from <address> [<ports>] to <address> [<ports>]`; ValueError otherwise."""
    words = text.split()
    if len(words) < 7 or words[:2] != ["permit", "out"] or "from" not in words or "to" not in words:
        raise ValueError(f"not an IPFilterRule (permit out <proto> from ... to ...): {text!r}")
    protocol = words[2]
    if protocol != "ip" and not (protocol.isdigit() and 0 <= int(protocol) <= 255):
        raise ValueError(f"protocol {protocol!r}: a number 0..255 or ip")
    at_from, at_to = words.index("from"), words.index("to")
    if not 3 == at_from < at_to:
        raise ValueError(f"not an IPFilterRule (from before to): {text!r}")
    source, source_ports = _end(words[at_from + 1 : at_to])
    destination, destination_ports = _end(words[at_to + 1 :])
    return Rule(source, source_ports, destination, destination_ports)


def _end(words: list[str]) -> tuple[str, frozenset[int]]:
    if not 1 <= len(words) <= 2:
        raise ValueError(f"an end of a rule is an address and its ports: {' '.join(words)!r}")
    address = words[0]
    if address not in ("any", "assigned"):
        ipaddress.ip_network(address, strict=False)  # ValueError for what is not an address
    return address, frozenset(_ports(words[1])) if len(words) == 2 else frozenset()


def _ports(text: str) -> set[int]:
    out: set[int] = set()
    for part in text.split(","):
        low, _, high = part.partition("-")
        if not low.isdigit() or (high and not high.isdigit()):
            raise ValueError(f"ports {text!r}: numbers, ranges a-b, separated by commas")
        first, last = int(low), int(high or low)
        if not 0 <= first <= last <= 65535 or last - first > 1024:
            raise ValueError(f"ports {text!r}: 0..65535, a range at most 1024 wide")
        out.update(range(first, last + 1))
    return out


def _names(address: str, host: str) -> bool:
    if address == "any":
        return True
    try:
        return ipaddress.ip_address(host) in ipaddress.ip_network(address, strict=False)
    except ValueError:
        return False


@dataclass
class NefSubscription:
    subscription_id: str
    scs_as_id: str
    uav: str
    body: dict[str, Any]  # as created and patched, `self` included
    ports: frozenset[int]  # the edge's ports its flows name
    status: str = "REQUESTED"  # then ALLOCATED, or FAILED (not admitted), or TERMINATED (by the network)
    settle_at_s: float = 0.0
    allocated_s: float | None = None
    next_report_s: float | None = None


@dataclass
class NefCounters:
    created: int = 0
    modified: int = 0
    deleted: int = 0
    refused: int = 0  # not admitted: FAILED_RESOURCES_ALLOCATION
    terminated: int = 0
    expired: int = 0  # qosDuration ran out
    reports: int = 0  # QOS_MONITORING notifications
    rejected: int = 0  # 4xx answers


@dataclass
class Nef:
    """Subscriptions of every SCS/AS at the emulated NEF. `devices`: drone id -> its CAMARA device
    object (the UE's addresses and phone number); `servers`: drone id -> its edge host."""

    cell: CellConfig
    devices: dict[str, dict[str, Any]]
    servers: dict[str, str]
    monotonic: Callable[[], float]
    root: str = ""  # the NEF's apiRoot, for the `self` links
    subscriptions: dict[str, NefSubscription] = field(default_factory=dict)
    counters: NefCounters = field(default_factory=NefCounters)

    # ---- the API ----------------------------------------------------------------------------------------

    def create(self, scs_as_id: str, body: Any) -> tuple[Answer, list[Notification]]:
        bad = _check(body, creating=True)
        if bad:
            return self._reject(400, "INVALID_MSG_FORMAT", bad), []
        uav = self._uav_of(body)
        if uav is None:
            return self._reject(404, "UE_NOT_FOUND", "no UE of this core has that identity"), []
        ports, refused = self._admissible(uav, body)
        if refused is not None:
            return refused, []
        if len(self.subscriptions) >= MAX_SUBSCRIPTIONS:
            return self._reject(403, "MAX_SUBSCRIPTIONS_REACHED", "too many subscriptions; delete some"), []
        now = self.monotonic()
        notes = self.advance()
        sid = uuid.uuid4().hex
        stored = dict(body) | {"self": f"{self.root}{API}/{scs_as_id}/subscriptions/{sid}"}
        sub = NefSubscription(sid, scs_as_id, uav, stored, ports, settle_at_s=now + self.cell.qod_setup_s)
        self.subscriptions[sid] = sub
        self.counters.created += 1
        notes += self.advance()
        return Answer(201, sub.body, location=stored["self"]), notes

    def get(self, scs_as_id: str, sid: str) -> Answer:
        sub = self._mine(scs_as_id, sid)
        return Answer(200, sub.body) if sub is not None else self._missing(sid)

    def all(self, scs_as_id: str, ip_addrs: str | None = None, mac_addrs: list[str] | None = None) -> Answer:
        """Every subscription of the SCS/AS, or those of the UEs named by the query (`ip-addrs`: a JSON
        array of IpAddr; `mac-addrs`: MacAddr48s); a 400 for a query the document does not allow."""
        names, bad = _ue_filter(ip_addrs, mac_addrs)
        if bad:
            return self._reject(400, "INVALID_QUERY_PARAM", bad)
        mine = [s.body for s in self.subscriptions.values() if s.scs_as_id == scs_as_id]
        if names is not None:
            mine = [b for b in mine if names(b)]
        return Answer(200, mine)

    def replace(self, scs_as_id: str, sid: str, body: Any) -> Answer:
        """PUT: the whole subscription anew (its UE stays; `self` is the NEF's), checked as a creation."""
        sub = self._mine(scs_as_id, sid)
        if sub is None:
            return self._missing(sid)
        if isinstance(body, dict):
            body = {k: v for k, v in body.items() if k != "self"}
        bad = _check(body, creating=True)
        if bad:
            return self._reject(400, "INVALID_MSG_FORMAT", bad)
        if self._uav_of(body) != sub.uav:
            return self._reject(
                400, "INVALID_MSG_FORMAT", "a subscription's UE cannot change; create another"
            )
        ports, refused = self._admissible(sub.uav, body)
        if refused is not None:
            return refused
        sub.body, sub.ports = body | {"self": sub.body["self"]}, ports
        if sub.allocated_s is not None and sub.status == "ALLOCATED":
            sub.next_report_s = self._first_report(sub, self.monotonic())
        self.counters.modified += 1
        return Answer(200, sub.body)

    def modify(self, scs_as_id: str, sid: str, changes: Any) -> Answer:
        """A merge patch (RFC 7396) of what PATCHABLE names; a null removes an optional field."""
        sub = self._mine(scs_as_id, sid)
        if sub is None:
            return self._missing(sid)
        if not isinstance(changes, dict) or not changes:
            return self._reject(400, "INVALID_MSG_FORMAT", "a patch is a non-empty JSON object")
        unknown = set(changes) - PATCHABLE
        if unknown:
            return self._reject(400, "INVALID_MSG_FORMAT", f"cannot patch {', '.join(sorted(unknown))}")
        merged = {k: v for k, v in (sub.body | changes).items() if v is not None}
        bad = _check(merged, creating=False)
        if bad:
            return self._reject(400, "INVALID_MSG_FORMAT", bad)
        ports, refused = self._admissible(sub.uav, merged)
        if refused is not None:
            return refused
        sub.body, sub.ports = merged, ports
        if "qosMonInfo" in changes and sub.allocated_s is not None:
            sub.next_report_s = self._first_report(sub, self.monotonic())
        self.counters.modified += 1
        return Answer(200, sub.body)

    def delete(self, scs_as_id: str, sid: str) -> Answer:
        """Deleted at once; the answer is the last notification's content (here: none, 204)."""
        sub = self._mine(scs_as_id, sid)
        if sub is None:
            return self._missing(sid)
        del self.subscriptions[sid]
        self.counters.deleted += 1
        return Answer(204)

    # ---- the network --------------------------------------------------------------------------------------

    def granted(self, uav: str, port: int) -> bool:
        """An allocated subscription gives this flow of the drone its QoS."""
        return any(
            s.uav == uav and s.status == "ALLOCATED" and port in s.ports for s in self.subscriptions.values()
        )

    def advance(self, delays: Delays | None = None) -> list[Notification]:
        """Allocate or refuse what was asked and end what ran out; with the cell's `delays`, the
        monitoring reports due too (a read through the API settles, the cell's clock reports)."""
        now = self.monotonic()
        notes: list[Notification] = []
        for sub in list(self.subscriptions.values()):
            if sub.status == "REQUESTED" and now >= sub.settle_at_s:
                notes += self._settle(sub, now)
            elif sub.status == "ALLOCATED":
                duration = sub.body.get("qosDuration")
                if (
                    isinstance(duration, int)
                    and sub.allocated_s is not None
                    and now >= sub.allocated_s + duration
                ):
                    self.counters.expired += 1
                    notes += self._end(sub)
                elif delays is not None and sub.next_report_s is not None and now >= sub.next_report_s:
                    notes += self._report(sub, delays)
                    sub.next_report_s = max(sub.next_report_s + _period(sub.body), now)
        return notes

    def end(self, uav: str = "") -> list[Notification]:
        """The network ends the allocated subscriptions of `uav` (or of every drone)."""
        notes: list[Notification] = []
        for sub in self.subscriptions.values():
            if sub.status == "ALLOCATED" and (not uav or sub.uav == uav):
                self.counters.terminated += 1
                notes += self._end(sub)
        return notes

    # ---- inside -----------------------------------------------------------------------------------------

    def _settle(self, sub: NefSubscription, now: float) -> list[Notification]:
        limit = self.cell.qod_max_sessions
        allocated = sum(s.status == "ALLOCATED" for s in self.subscriptions.values())
        if limit >= 0 and allocated >= limit:
            sub.status = "FAILED"
            self.counters.refused += 1
            return self._notify(sub, [{"event": "FAILED_RESOURCES_ALLOCATION"}])
        sub.status, sub.allocated_s = "ALLOCATED", now
        sub.next_report_s = self._first_report(sub, now)
        return self._notify(sub, [{"event": "SUCCESSFUL_RESOURCES_ALLOCATION"}, {"event": "QOS_GUARANTEED"}])

    def _end(self, sub: NefSubscription) -> list[Notification]:
        sub.status, sub.next_report_s = "TERMINATED", None
        return self._notify(sub, [{"event": "SESSION_TERMINATION"}])

    def _first_report(self, sub: NefSubscription, now: float) -> float | None:
        asked = "QOS_MONITORING" in (sub.body.get("events") or []) and isinstance(
            sub.body.get("qosMonInfo"), dict
        )
        return now + _period(sub.body) if asked else None

    def _report(self, sub: NefSubscription, delays: Delays) -> list[Notification]:
        uplink, downlink, round_trip = delays(sub.uav)
        params = set((sub.body.get("qosMonInfo") or {}).get("reqQosMonParams") or [])
        report: dict[str, Any] = {}
        for param, key, value in (
            ("UPLINK", "ulDelays", uplink),
            ("DOWNLINK", "dlDelays", downlink),
            ("ROUND_TRIP", "rtDelays", round_trip),
        ):
            if param in params:
                report[key] = [value]
        self.counters.reports += 1
        return self._notify(sub, [{"event": "QOS_MONITORING", "qosMonReports": [report]}])

    def _notify(self, sub: NefSubscription, events: list[dict[str, Any]]) -> list[Notification]:
        sink = sub.body.get("notificationDestination", "")
        wanted = [e for e in events if e["event"] in (sub.body.get("events") or [])]
        if not sink or not wanted:
            return []
        data = {"transaction": sub.body["self"], "eventReports": wanted}
        return [Notification(sink, None, data, content_type=JSON)]

    def _uav_of(self, body: dict[str, Any]) -> str | None:
        for uav, device in self.devices.items():
            ipv4 = device.get("ipv4Address") or {}
            if body.get("ueIpv4Addr") and body["ueIpv4Addr"] in (
                ipv4.get("privateAddress"),
                ipv4.get("publicAddress"),
            ):
                return uav
            if body.get("ueIpv6Addr") and _names(
                str(device.get("ipv6Address", "")) or "::/128", body["ueIpv6Addr"]
            ):
                return uav
            phone = str(device.get("phoneNumber", "")).lstrip("+")
            if body.get("gpsi") and phone and body["gpsi"] == f"msisdn-{phone}":
                return uav
        return None

    def _flows(self, uav: str, flows: list[dict[str, Any]]) -> tuple[frozenset[int], Answer | None]:
        """The edge ports the flows name; a 400 for a rule that does not parse, or whose edge end is not
        this drone's edge host."""
        host, ports = self.servers.get(uav, ""), set[int]()
        for flow in flows:
            for text in flow.get("flowDescriptions") or []:
                try:
                    rule = parse_rule(text)
                except ValueError as exc:
                    return frozenset(), self._reject(400, "INVALID_MSG_FORMAT", str(exc))
                if _names(rule.destination, host) and rule.destination_ports:
                    ports |= rule.destination_ports
                elif _names(rule.source, host) and rule.source_ports:
                    ports |= rule.source_ports
                else:
                    flow_id = flow.get("flowId")
                    why = f"flow {flow_id}: no end of {text!r} is this UE's edge ({host}) with a port"
                    return frozenset(), self._reject(400, "INVALID_MSG_FORMAT", why)
        return frozenset(ports), None

    def _admissible(self, uav: str, body: dict[str, Any]) -> tuple[frozenset[int], Answer | None]:
        """What create, replace and modify check alike: the edge ports the flows name and a QoS reference
        this core offers; the refusal of the first that fails."""
        ports, refused = self._flows(uav, body["flowInfo"])
        return ports, refused if refused is not None else self._unknown_reference(body)

    def _unknown_reference(self, body: dict[str, Any]) -> Answer | None:
        """A 403 for a qosReference this core does not offer (None when it does), on create and patch."""
        if body["qosReference"] in self.cell.qod_profiles:
            return None
        offered = ", ".join(self.cell.qod_profiles)
        why = f"qosReference {body['qosReference']} is not one of this core's ({offered})"
        return self._reject(403, "QOS_REFERENCE_NOT_AUTHORIZED", why)

    def _mine(self, scs_as_id: str, sid: str) -> NefSubscription | None:
        sub = self.subscriptions.get(sid)
        return sub if sub is not None and sub.scs_as_id == scs_as_id else None

    def _missing(self, sid: str) -> Answer:
        return self._reject(404, "RESOURCE_NOT_FOUND", f"no subscription {sid} of this SCS/AS")

    def _reject(self, status: int, cause: str, detail: str) -> Answer:
        self.counters.rejected += 1
        return problem(status, cause, detail)


def _period(body: dict[str, Any]) -> float:
    period = (body.get("qosMonInfo") or {}).get("repPeriod")
    return float(period) if isinstance(period, int) and period > 0 else 1.0


UeFilter = Callable[[dict[str, Any]], bool]


def _ip_addr(item: Any) -> ipaddress.IPv4Network | ipaddress.IPv6Network | None:
    """An IpAddr (TS 29.571: one of ipv4Addr, ipv6Addr, ipv6Prefix, each by its pattern) as a network."""
    if not isinstance(item, dict):
        return None
    named = [(k, item[k]) for k in IP_ADDR if k in item]
    if len(named) != 1 or not isinstance(named[0][1], str):
        return None
    key, text = named[0]
    if not all(pattern.fullmatch(text) for pattern in IP_ADDR[key]):
        return None
    try:
        return ipaddress.ip_network(text, strict=False)
    except ValueError:
        return None


def _ue_filter(ip_addrs: str | None, mac_addrs: list[str] | None) -> tuple[UeFilter | None, str]:
    """Whether a subscription names one of the UEs a read asks for (None: every UE), or what is wrong
    with the query. An IpAddr is an ipv4Addr, an ipv6Addr or an ipv6Prefix (TS 29.571)."""
    if ip_addrs is None and not mac_addrs:
        return None, ""
    networks: list[ipaddress.IPv4Network | ipaddress.IPv6Network] = []
    if ip_addrs is not None:
        try:
            listed = json.loads(ip_addrs)
        except ValueError:
            return None, "ip-addrs: a JSON array of IpAddr"
        if not isinstance(listed, list) or not listed:
            return None, "ip-addrs: a JSON array of at least one IpAddr"
        for item in listed:
            network = _ip_addr(item)
            if network is None:
                why = "exactly one of ipv4Addr, ipv6Addr, ipv6Prefix, as TS 29.571 writes it"
                return None, f"ip-addrs: {item!r} is not an IpAddr ({why})"
            networks.append(network)
    macs: set[str] = set()
    for mac in mac_addrs or []:
        if not MAC48.fullmatch(mac):
            return None, f"mac-addrs: {mac!r} is not a MacAddr48 (aa-bb-cc-dd-ee-ff)"
        macs.add(mac.lower())

    def names(body: dict[str, Any]) -> bool:
        if str(body.get("macAddr", "")).lower() in macs:
            return True
        return any(
            _names(str(n), str(body.get(k, ""))) for n in networks for k in ("ueIpv4Addr", "ueIpv6Addr")
        )

    return names, ""


def _check(body: Any, *, creating: bool) -> str:
    """What is wrong with a subscription's content ("" when nothing)."""
    if not isinstance(body, dict):
        return "the body is not a JSON object"
    if not isinstance(body.get("notificationDestination"), str) or not body["notificationDestination"]:
        return "notificationDestination is required"
    named = [k for k in IDENTITIES if body.get(k)]
    if len(named) != 1:
        return "name the UE by exactly one of ueIpv4Addr, ueIpv6Addr, gpsi"
    flows = body.get("flowInfo")
    if (
        not isinstance(flows, list)
        or not flows
        or not all(
            isinstance(f, dict)
            and isinstance(f.get("flowId"), int)
            and isinstance(f.get("flowDescriptions"), list)
            for f in flows
        )
    ):
        return "flowInfo: at least one flow, each with its flowId and flowDescriptions"
    if not isinstance(body.get("qosReference"), str) or not body["qosReference"]:
        return "qosReference is required (this core grants QoS by reference)"
    duration = body.get("qosDuration")
    if duration is not None and (not isinstance(duration, int) or duration < 1):
        return "qosDuration: seconds, at least 1"
    events = body.get("events")
    if events is not None and (not isinstance(events, list) or not all(isinstance(e, str) for e in events)):
        return "events: a list of UserPlaneEvent"
    if creating and body.get("self"):
        return "self is the NEF's to give"
    return ""
