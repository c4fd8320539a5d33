"""The emulated cell as an operator: QoD sessions, what they grant, and how the API answers.

Pure logic with the clocks passed in; sim/network/control_api.py serves it over HTTP. A session names a device
and the application server's ports; while it is AVAILABLE the bearers of that device whose target port
it names get their priority weight (sim/network/cell.py asks `granted`). A session is REQUESTED for
[cell] qod_setup_s, then AVAILABLE, or UNAVAILABLE/NETWORK_TERMINATED when the admission limit
(qod_max_sessions) is reached, as an operator that cannot grant answers. It expires after its duration
(DURATION_EXPIRED), a timeline event can end it (NETWORK_TERMINATED), and an ended session keeps its
resources until it is deleted: creating another for the same device and ports before that is a 409,
as the API says. Every status change is a notification for the session's sink.
"""

from __future__ import annotations

import ipaddress
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from dynqos.common.camara import EVENT_TYPE, ports_named, rfc3339
from dynqos.common.config import CellConfig, CellEventConfig
from dynqos.sim.network.cell_core import Effect
from dynqos.sim.network.operator_schema import (
    CREATE_SESSION_STRICT,
    CREATE_SESSION_STRICT_1_2,
    EXTEND_SESSION_STRICT,
    RETRIEVE_PROFILES_STRICT,
    RETRIEVE_SESSIONS_STRICT,
    problem,
)

ENDED_KEPT_S = (
    360.0  # an ended session not deleted is dropped this long after it ended (the spec's "at earliest")
)
MAX_SESSIONS = 10_000  # all sessions kept, ended ones included: a client that never deletes cannot grow this
TOO_MANY_RETRY_AFTER_S = 5  # the Retry-After of that 429: sessions are deleted within seconds of their end


@dataclass
class Session:
    session_id: str
    uav: str
    device: dict[str, Any]
    body: dict[str, Any]  # the create request (applicationServer, ports, qosProfile, sink...)
    duration_s: int
    status: str = "REQUESTED"
    status_info: str = ""
    settle_at_s: float = 0.0
    started_wall: float | None = None
    started_s: float | None = None
    ended_s: float | None = None
    ended_wall: float | None = None

    def ports(self) -> set[int]:
        return ports_named(self.body.get("applicationServerPorts"))


@dataclass(frozen=True, slots=True)
class Answer:
    status: int
    body: Any = None
    retry_after_s: int | None = None  # a Retry-After header (429)
    location: str = ""  # a Location header (a created resource's URI)
    content_type: str = "application/json"  # a NEF's error is application/problem+json


@dataclass(frozen=True, slots=True)
class Notification:
    sink: str
    credential: dict[str, Any] | None
    event: dict[str, Any]
    content_type: str = "application/cloudevents+json"  # CAMARA's; the NEF's are plain JSON


@dataclass
class QodCounters:
    created: int = 0
    extended: int = 0
    deleted: int = 0
    refused: int = 0  # admission: created but never AVAILABLE
    expired: int = 0
    terminated: int = 0  # ended by the network (timeline event)
    conflicts: int = 0
    rejected: int = 0  # 4xx answers other than 409


def _rfc3339(wall_s: float) -> str:
    return rfc3339(wall_s, "milliseconds")


def error(status: int, code: str, message: str) -> Answer:
    return Answer(status, {"status": status, "code": code, "message": message})


UNSUPPORTED_NAI = (
    "networkAccessIdentifier is not supported (quality-on-demand v1.1.0); name the device by phoneNumber, "
    "ipv4Address or ipv6Address"
)


def _only_nai(device: Any) -> bool:
    """The device is named by a networkAccessIdentifier alone: v1.1.0 keeps it in the schema for the
    future and allows no use of it, so nothing the operator supports identifies the device."""
    return isinstance(device, dict) and set(device) == {"networkAccessIdentifier"}


def _same_subnet(given: Any, known: Any) -> bool:
    """An IPv6 device is named by its observed address or by any address in the /64 allocated to it."""
    try:
        address = ipaddress.IPv6Address(str(given))
        subnet = ipaddress.IPv6Network(str(known), strict=False)
    except ValueError:
        return False
    return address in (subnet if subnet.prefixlen < 128 else subnet.supernet(new_prefix=64))


def _device_matches(given: dict[str, Any], known: dict[str, Any]) -> bool:
    """The request's device names the known one by any supported identifier both give."""
    if "phoneNumber" in given and given["phoneNumber"] == known.get("phoneNumber"):
        return True
    if (
        "ipv6Address" in given
        and "ipv6Address" in known
        and _same_subnet(given["ipv6Address"], known["ipv6Address"])
    ):
        return True
    ipv4, mine = given.get("ipv4Address"), known.get("ipv4Address")
    if (
        isinstance(ipv4, dict)
        and isinstance(mine, dict)
        and ipv4.get("publicAddress") == mine.get("publicAddress")
    ):
        return any(k in ipv4 and ipv4[k] == mine.get(k) for k in ("privateAddress", "publicPort"))
    return False


def _same_address(given: Any, address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> bool:
    try:
        return ipaddress.ip_address(str(given)) == address
    except ValueError:
        return False


def _server_matches(server: dict[str, Any], host: str) -> bool:
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return True  # a host name: the emulator cannot tell; accept
    if "ipAddresses" in server:  # 1.2.0: a list of single addresses
        return any(_same_address(a, address) for a in server["ipAddresses"])
    for key in ("ipv4Address", "ipv6Address"):
        if key in server:
            try:
                if address in ipaddress.ip_network(server[key], strict=False):
                    return True
            except ValueError:
                continue
    return False


@dataclass
class Operator:
    """Sessions of the emulated operator. `devices`: drone id -> its CAMARA device object."""

    cell: CellConfig
    devices: dict[str, dict[str, Any]]
    servers: dict[str, str]  # drone id -> the host of its priority bearer's target (what the network sees)
    monotonic: Callable[[], float]
    wall: Callable[[], float]
    sessions: dict[str, Session] = field(default_factory=dict)
    counters: QodCounters = field(default_factory=QodCounters)
    source: str = "dynqos-sim-cell"
    # its profiles now ([cell] qod_profiles and the rest at start; a qod_profile event changes them)
    offered: list[str] = field(default_factory=list)
    inactive: set[str] = field(default_factory=set)
    caps: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.offered = list(dict.fromkeys((*self.cell.qod_profiles, *self.cell.qod_inactive_profiles)))
        self.inactive = set(self.cell.qod_inactive_profiles)
        self.caps = dict(self.cell.qod_profile_max_duration_s)

    # ---- the API ----------------------------------------------------------------------------------------

    def create(self, body: Any, subject: str = "") -> tuple[Answer, list[Notification]]:
        """`subject`: the drone a three-legged token names ("": a two-legged token)."""
        strict = CREATE_SESSION_STRICT_1_2 if self.cell.qod_api_version == "1.2.0" else CREATE_SESSION_STRICT
        bad = problem(strict, body)
        if bad is not None:
            return self._reject(400, "INVALID_ARGUMENT", bad), []
        uav, refused = self._identified(body, subject)
        if refused is not None:
            return refused, []
        server = body["applicationServer"]
        if not _server_matches(server, self.servers.get(uav, "")):
            return self._reject(400, "INVALID_ARGUMENT", f"this device has no flow to {server}"), []
        if body["qosProfile"] not in self.offered or body["qosProfile"] in self.inactive:
            profiles = ", ".join(p for p in self.offered if p not in self.inactive)
            why = f"profile {body['qosProfile']} is not offered here (offered: {profiles})"
            return self._reject(422, "QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE", why), []
        now = self.monotonic()
        self._expire_and_settle(now)
        ports = ports_named(body.get("applicationServerPorts"))
        for other in self.sessions.values():
            if other.uav == uav and (not ports or not other.ports() or ports & other.ports()):
                self.counters.conflicts += 1
                state = "ended but not deleted" if other.status == "UNAVAILABLE" else other.status
                return error(
                    409, "CONFLICT", f"session {other.session_id} for this flow exists ({state})"
                ), []
        if len(self.sessions) >= MAX_SESSIONS:
            answer = error(429, "TOO_MANY_REQUESTS", "too many sessions; delete some")
            return replace(answer, retry_after_s=TOO_MANY_RETRY_AFTER_S), []
        duration = min(body["duration"], self.max_duration_s(body["qosProfile"]))
        session = Session(str(uuid.uuid4()), uav, body.get("device", {}), body, duration)
        session.settle_at_s = now + self.cell.qod_setup_s
        self.sessions[session.session_id] = session
        self.counters.created += 1
        notes = self._expire_and_settle(now)
        return Answer(201, self.info(session)), notes

    def _session(self, session_id: str, subject: str) -> Session | None:
        """A session by id; a three-legged token sees only its own device's (another's does not exist)."""
        session = self.sessions.get(session_id)
        return None if session is None or (subject and session.uav != subject) else session

    def get(self, session_id: str, subject: str = "") -> Answer:
        session = self._session(session_id, subject)
        return (
            error(404, "NOT_FOUND", "the session does not exist")
            if session is None
            else Answer(200, self.info(session))
        )

    def extend(self, session_id: str, body: Any, subject: str = "") -> Answer:
        session = self._session(session_id, subject)
        if session is None:
            return self._reject(404, "NOT_FOUND", "the session does not exist")
        bad = problem(EXTEND_SESSION_STRICT, body)
        if bad is not None:
            return self._reject(400, "INVALID_ARGUMENT", bad)
        if session.status != "AVAILABLE":
            self.counters.conflicts += 1
            return error(
                409, "QUALITY_ON_DEMAND.SESSION_EXTENSION_NOT_ALLOWED", f"the session is {session.status}"
            )
        session.duration_s = min(
            session.duration_s + body["requestedAdditionalDuration"],
            self.max_duration_s(session.body["qosProfile"]),
        )
        self.counters.extended += 1
        return Answer(200, self.info(session))

    def delete(self, session_id: str, subject: str = "") -> tuple[Answer, list[Notification]]:
        session = self._session(session_id, subject)
        if session is not None:
            del self.sessions[session_id]
        if session is None:
            return self._reject(404, "NOT_FOUND", "the session does not exist"), []
        self.counters.deleted += 1
        notes = []
        if session.status == "AVAILABLE":
            notes = self._end(session, "DELETE_REQUESTED", self.monotonic())
        return Answer(204), notes

    def retrieve(self, body: Any, subject: str = "") -> Answer:
        bad = problem(RETRIEVE_SESSIONS_STRICT, body)
        if bad is not None:
            return self._reject(400, "INVALID_ARGUMENT", bad)
        uav, refused = self._identified(body, subject)
        if refused is not None:
            return refused
        return Answer(200, [self.info(s) for s in self.sessions.values() if s.uav == uav])

    # ---- the QoS Profiles API (qos-profiles v1.1.0) ----------------------------------------------------

    def profiles(self, body: Any) -> Answer:
        """retrieve-qos-profiles: every profile offered, filtered by `name` and `status` when given."""
        if not isinstance(body, dict):
            return self._reject(400, "INVALID_ARGUMENT", "the body must be a QosProfileDeviceRequest object")
        bad = problem(RETRIEVE_PROFILES_STRICT, body)  # unknown fields, a device that is no Device
        if bad:
            return self._reject(400, "INVALID_ARGUMENT", bad)
        if "device" in body and _only_nai(body["device"]):
            return self._reject(422, "UNSUPPORTED_IDENTIFIER", UNSUPPORTED_NAI)
        if "device" in body and self._uav_of(body["device"]) is None:
            return self._reject(404, "IDENTIFIER_NOT_FOUND", "device identifier not found")
        listed = [self.profile_info(name) for name in self._listed()]
        return Answer(
            200, [p for p in listed if all(p[k] == body[k] for k in ("name", "status") if k in body)]
        )

    def profile(self, name: str) -> Answer:
        if name not in self._listed():
            return self._reject(404, "NOT_FOUND", f"no QoS profile named {name}")
        return Answer(200, self.profile_info(name))

    def profile_info(self, name: str) -> dict[str, Any]:
        """A QosProfile: what this emulated operator enforces of it (status, the session duration range)."""
        return {
            "name": name,
            "description": "dynqos emulated cell: the priority bearer's scheduling weight while AVAILABLE",
            "status": "INACTIVE" if name in self.inactive else "ACTIVE",
            "minDuration": {"value": 1, "unit": "Seconds"},
            "maxDuration": {"value": self.max_duration_s(name), "unit": "Seconds"},
        }

    def max_duration_s(self, profile: str) -> int:
        """What a session of `profile` may last, extensions included."""
        return self.caps.get(profile, self.cell.qod_max_duration_s)

    def _listed(self) -> list[str]:
        return self.offered

    def apply(self, effect: Effect) -> list[Notification]:
        """What a timeline event asks of the operator: end sessions, or change a profile."""
        if effect.profile is not None:
            self.change_profile(effect.profile)
        return self.end_sessions(effect.end_qod) if effect.end_qod is not None else []

    def change_profile(self, event: CellEventConfig) -> None:
        """A timeline's qod_profile event: the profile's status (WITHDRAWN: no longer listed; ACTIVE
        lists it again) and its maxDuration. Sessions already made keep theirs."""
        name = event.profile
        if event.status == "WITHDRAWN":
            self.offered = [p for p in self.offered if p != name]
        elif event.status:
            if name not in self.offered:
                self.offered.append(name)
            (self.inactive.add if event.status == "INACTIVE" else self.inactive.discard)(name)
        if event.max_duration_s:
            self.caps[name] = event.max_duration_s

    # ---- the network --------------------------------------------------------------------------------------

    def advance(self) -> list[Notification]:
        """Settle REQUESTED sessions and expire the ones past their duration; called every few TTIs."""
        return self._expire_and_settle(self.monotonic())

    def end_sessions(self, uav: str = "") -> list[Notification]:
        """The network ends the AVAILABLE sessions of `uav` (or of every drone): NETWORK_TERMINATED."""
        now = self.monotonic()
        notes: list[Notification] = []
        for session in list(self.sessions.values()):
            if session.status != "UNAVAILABLE" and (not uav or session.uav == uav):
                self.counters.terminated += 1
                notes += self._end(session, "NETWORK_TERMINATED", now)
        return notes

    def granted(self, uav: str, port: int) -> bool:
        """A QoD session gives this flow of the drone priority (a booking may too: operator_apis.py)."""
        return any(
            s.uav == uav and s.status == "AVAILABLE" and (not s.ports() or port in s.ports())
            for s in self.sessions.values()
        )

    def open_sessions(self) -> list[dict[str, Any]]:
        """Sessions not deleted (an ended one still holds resources until deleted)."""
        return [self.info(s) | {"uav": s.uav} for s in self.sessions.values()]

    # ---- inside -----------------------------------------------------------------------------------------

    def _expire_and_settle(self, now: float) -> list[Notification]:
        notes: list[Notification] = []
        for session in list(self.sessions.values()):
            if session.status == "REQUESTED" and now >= session.settle_at_s:
                if self._admits():
                    session.status = "AVAILABLE"
                    session.started_s, session.started_wall = now, self.wall()
                    notes += self._notify(session)
                else:
                    self.counters.refused += 1
                    notes += self._end(session, "NETWORK_TERMINATED", now)
            elif session.status == "AVAILABLE" and session.started_s is not None:
                if now >= session.started_s + session.duration_s:
                    self.counters.expired += 1
                    notes += self._end(session, "DURATION_EXPIRED", session.started_s + session.duration_s)
            elif session.ended_s is not None and now - session.ended_s > ENDED_KEPT_S:
                del self.sessions[session.session_id]
        return notes

    def _admits(self) -> bool:
        limit = self.cell.qod_max_sessions
        return limit < 0 or sum(s.status == "AVAILABLE" for s in self.sessions.values()) < limit

    def _end(self, session: Session, why: str, at_s: float) -> list[Notification]:
        session.status, session.status_info = "UNAVAILABLE", why
        session.ended_s = at_s
        session.ended_wall = self.wall() - (self.monotonic() - at_s)
        return self._notify(session)

    def _notify(self, session: Session) -> list[Notification]:
        data = {"sessionId": session.session_id, "qosStatus": session.status}
        if session.status_info:
            data["statusInfo"] = session.status_info
        return self.cloud_event(session.body, EVENT_TYPE, data)

    def cloud_event(self, body: dict[str, Any], event_type: str, data: dict[str, Any]) -> list[Notification]:
        """The CloudEvent that tells a request's sink (if it named one) what became of it: a QoD session's
        status here, a booking's in sim/network/booking.py."""
        sink = body.get("sink")
        if not sink:
            return []
        event = {
            "id": str(uuid.uuid4()),
            "source": self.source,
            "type": event_type,
            "specversion": "1.0",
            "datacontenttype": "application/json",
            "time": _rfc3339(self.wall()),
            "data": data,
        }
        return [Notification(sink, body.get("sinkCredential"), event)]

    def info(self, session: Session) -> dict[str, Any]:
        """The session as a CAMARA SessionInfo."""
        out = {k: v for k, v in session.body.items() if k not in ("duration", "device", "sinkCredential")}
        if session.device:  # one identifier in a response; none for a three-legged token's session
            out["device"] = dict([next(iter(session.device.items()))])
        out |= {"sessionId": session.session_id, "duration": session.duration_s, "qosStatus": session.status}
        if session.started_wall is not None:
            out["startedAt"] = _rfc3339(session.started_wall)
            if session.status == "AVAILABLE":
                out["expiresAt"] = _rfc3339(session.started_wall + session.duration_s)
        if session.status == "UNAVAILABLE":
            out["statusInfo"] = session.status_info
            if session.ended_wall is not None:
                out["expiresAt"] = _rfc3339(session.ended_wall)
            if session.started_s is not None and session.ended_s is not None:
                out["duration"] = max(1, round(session.ended_s - session.started_s))
        return out

    def _identified(self, body: dict[str, Any], subject: str) -> tuple[str, Answer | None]:
        """The drone a request is about: the one its three-legged token names (then the body must not
        name a device), or the one its `device` names (a two-legged token)."""
        if subject:
            if "device" in body:
                why = "the access token already identifies the device: leave `device` out"
                return "", self._reject(422, "UNNECESSARY_IDENTIFIER", why)
            return subject, None
        if "device" not in body:
            why = "the device cannot be identified (two-legged token)"
            return "", self._reject(422, "MISSING_IDENTIFIER", why)
        if _only_nai(body["device"]):
            return "", self._reject(422, "UNSUPPORTED_IDENTIFIER", UNSUPPORTED_NAI)
        uav = self._uav_of(body["device"])
        if uav is None:
            return "", self._reject(404, "IDENTIFIER_NOT_FOUND", "device identifier not found")
        return uav, None

    def identify(self, body: dict[str, Any], subject: str) -> tuple[str, Answer | None]:
        """The drone a request of any of this operator's APIs is about (or the refusal)."""
        return self._identified(body, subject)

    def _uav_of(self, device: dict[str, Any]) -> str | None:
        return next((uav for uav, known in self.devices.items() if _device_matches(device, known)), None)

    def _reject(self, status: int, code: str, message: str) -> Answer:
        self.counters.rejected += 1
        return error(status, code, message)
