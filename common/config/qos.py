"""Config sections of the QoS agent: [qos], [qos.camara] with the drones' device identities, and
[qos.arbiter] ([qos.nef] is in nef.py)."""

from __future__ import annotations

import ipaddress
import re
from dataclasses import asdict, dataclass, field
from typing import Annotated, Any, Literal

from dynqos.common.camara import AGENT_SCOPE
from dynqos.common.config.nef import NefConfig
from dynqos.common.config.validate import (
    In,
    _check_name,
    _check_replica_id,
    _host_port,
    _loopback,
    _require,
    checked,
)
from dynqos.common.errors import ConfigError
from dynqos.common.keys import UAV_ID_PATTERN

_PHONE_NUMBER = re.compile(r"\+[1-9][0-9]{4,14}")
SECONDS_3600 = In(0, 3600, "must be in 0..3600 s")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class DeviceIpv4Config:
    """CAMARA DeviceIpv4Addr: the public address, with the private address or the public port."""

    publicAddress: str = ""
    privateAddress: str = ""
    publicPort: Annotated[int, In(0, 65535, "must be a port in 1..65535 (0: not given)")] = 0

    def __post_init__(self) -> None:
        for name in ("publicAddress", "privateAddress"):
            value = getattr(self, name)
            if value:
                try:
                    ipaddress.IPv4Address(value)
                except ValueError:
                    raise ConfigError(name, f"{value!r} is not an IPv4 address") from None
        if self.privateAddress or self.publicPort:
            _require(
                bool(self.publicAddress), "publicAddress", "is required with privateAddress or publicPort"
            )
        if self.publicAddress:
            _require(
                bool(self.privateAddress or self.publicPort),
                "publicAddress",
                "needs privateAddress or publicPort as well (CAMARA DeviceIpv4Addr)",
            )


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class DeviceConfig:
    """A drone's identity on the operator's network: a CAMARA `device` object (at least one identifier)."""

    phoneNumber: str = ""
    networkAccessIdentifier: str = ""
    ipv4Address: DeviceIpv4Config = field(default_factory=DeviceIpv4Config)
    ipv6Address: str = ""

    def __post_init__(self) -> None:
        if self.phoneNumber:
            _require(
                _PHONE_NUMBER.fullmatch(self.phoneNumber) is not None,
                "phoneNumber",
                f"{self.phoneNumber!r} is not E.164 with a leading + (e.g. +46700000001)",
            )
        if self.ipv6Address:
            try:
                ipaddress.IPv6Address(self.ipv6Address)
            except ValueError:
                raise ConfigError("ipv6Address", f"{self.ipv6Address!r} is not an IPv6 address") from None
        ids = "phoneNumber, ipv4Address, ipv6Address, networkAccessIdentifier"
        _require(bool(self.as_api()), "device", f"needs at least one of {ids}")

    def as_api(self) -> dict[str, Any]:
        """The CAMARA `device` object: only the identifiers given."""
        out: dict[str, Any] = {}
        if self.phoneNumber:
            out["phoneNumber"] = self.phoneNumber
        if self.networkAccessIdentifier:
            out["networkAccessIdentifier"] = self.networkAccessIdentifier
        ipv4 = {k: v for k, v in asdict(self.ipv4Address).items() if v}
        if ipv4:
            out["ipv4Address"] = ipv4
        if self.ipv6Address:
            out["ipv6Address"] = self.ipv6Address
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class CamaraConfig:
    """[qos.camara]: a CAMARA Quality-on-Demand API (v1.1.0) the agent asks for QoS sessions."""

    api_root: str = ""  # e.g. https://api.operator.example/quality-on-demand/v1
    token_url: str = ""  # OAuth2 token endpoint for client credentials ("" = no token)
    client_id: str = ""
    client_secret_file: str = ""  # a file holding the client secret (never the secret itself)
    # or private_key_jwt (RFC 7523, what CAMARA's identity rules ask): a PEM key (RSA or EC P-256) that
    # signs a client assertion for each token; its public key is registered with the operator
    client_key_file: str = ""
    scope: str = AGENT_SCOPE  # asked with each token: the scopes of every call the agent makes
    # TLS to the operator: a CA bundle to verify it ("" = the system's), and a client certificate and its
    # key for operators that want mutual TLS (both or neither)
    ca_file: str = ""
    tls_cert_file: str = ""
    tls_key_file: str = ""
    # three-legged: a token per drone (RFC 7523 JWT-bearer grant, the assertion's `sub` the drone's
    # login hint, tel:<phoneNumber>), and requests that name no device (needs client_key_file)
    three_legged: bool = False
    # or fixed API-key headers, as aggregators authenticate: a file of `Name: value` lines sent with
    # every call (no token_url then)
    headers_file: str = ""
    qos_profile: str = "QOS_E"
    # Before any session, read the operator's QoS Profiles API: refuse to start if qos_profile is not
    # offered or not ACTIVE, fit duration_s into its min..max (docs/qos.md, "Profiles first")
    check_profile: bool = True
    profiles_root: str = ""  # e.g. https://api.operator.example/qos-profiles/v1 ("" = beside api_root)
    # Predictive Connectivity Data 0.1.0 ("" = beside api_root: {apiRoot}/predictive-connectivity-data/v0.1)
    connectivity_root: str = ""
    booking_root: str = ""  # QoS Booking 0.1.0 ("" = beside api_root: {apiRoot}/qos-booking/v0.1)
    # ... and again this often, and at once when a create is refused as if the profile had changed
    profile_recheck_s: Annotated[float, In(1, 86400, "must be in 1..86400 s")] = 300.0
    duration_s: Annotated[int, In(1, 10**7, "must be in 1..10000000 s")] = (
        600  # requested per session; extended while priority is still wanted
    )
    extend_before_s: float = 30.0  # extend when the session has less than this left
    # A session the operator capped (an extend did not move its end) is replaced this long before it ends
    renew_before_s: float = 2.0
    application_server: str = ""  # the edge address the network sees ("" = [zenoh] edge_host)
    # The QoD version the operator serves. With 1.2.0 the server may instead be named by a list of single
    # addresses (applicationServer.ipAddresses), e.g. an edge router reachable at two sites
    api_version: Literal["1.1.0", "1.2.0"] = "1.1.0"
    application_server_addresses: tuple[str, ...] = ()
    sink: str = ""  # notifications URL given to the operator ("" = polling only)
    sink_listen: str = ""  # host:port the agent serves that URL on ("" = no listener)
    poll_interval_s: Annotated[float, In(0.01, 60, "must be in 0.01..60 s")] = (
        0.2  # how often a REQUESTED session is read until it settles
    )
    timeout_s: Annotated[float, In(0.05, 60, "must be in 0.05..60 s")] = (
        2.0  # every HTTP call ends within this
    )
    retry_after_denied_s: Annotated[float, In(0.1, 3600, "must be in 0.1..3600 s")] = (
        10.0  # a denied drone asks again after this (doubling, up to 8x)
    )
    devices: dict[str, DeviceConfig] = field(default_factory=dict)  # drone id -> its device

    def __post_init__(self) -> None:
        for name in ("api_root", "token_url", "sink", "profiles_root", "connectivity_root", "booking_root"):
            url = getattr(self, name)
            _require(not url or url.startswith(("http://", "https://")), name, "must be an http(s) URL")
            # tokens, device identities and the sink's credential cross these: TLS, except on this host
            plain_http_ok = not url.startswith("http://") or _loopback(url)
            _require(plain_http_ok, name, "must be https:// (plain http only to 127.0.0.0/8, ::1, localhost)")
        _require(
            len(self.qos_profile) >= 3
            and re.fullmatch(r"[A-Za-z0-9_.-]{3,256}", self.qos_profile) is not None,
            "qos_profile",
            "must be 3..256 of A-Z a-z 0-9 _ . -",
        )
        _require(0 <= self.extend_before_s < self.duration_s, "extend_before_s", "must be in 0..duration_s")
        _require(0 <= self.renew_before_s < self.duration_s, "renew_before_s", "must be in 0..duration_s")
        self._check_addresses()
        if self.sink_listen:
            _host_port(self.sink_listen, "sink_listen")
        if self.token_url:
            _require(bool(self.client_id), "client_id", "is required with token_url")
            one_credential = bool(self.client_secret_file) != bool(self.client_key_file)
            _require(one_credential, "client_secret_file", "with token_url, give it or client_key_file (one)")
        _require(
            not (self.headers_file and self.token_url), "headers_file", "is instead of token_url, not with it"
        )
        _require(
            bool(self.tls_cert_file) == bool(self.tls_key_file),
            "tls_cert_file",
            "and tls_key_file go together",
        )
        if self.three_legged:  # the drone's token is asked with an assertion naming its phone number
            _require(
                bool(self.token_url and self.client_key_file),
                "three_legged",
                "needs token_url and client_key_file",
            )
            for uav, device in self.devices.items():
                _require(bool(device.phoneNumber), f"devices.{uav}", "needs a phoneNumber with three_legged")
        for uav in self.devices:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"devices.{uav}", "is not a drone id")

    def _check_addresses(self) -> None:
        addresses = self.application_server_addresses
        if not addresses:
            return
        key = "application_server_addresses"
        _require(self.api_version == "1.2.0", key, 'needs api_version = "1.2.0" (1.1.0 has no address list)')
        _require(not self.application_server, key, "is instead of application_server, not with it")
        _require(
            len(addresses) <= 16 and len(set(addresses)) == len(addresses),
            key,
            "must be at most 16 different addresses",
        )
        for address in addresses:
            try:
                ipaddress.ip_address(address)
            except ValueError:
                raise ConfigError(key, f"{address!r} is not a single IP address (no mask)") from None


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class ArbiterConfig:
    """[qos.arbiter]: the budget and the timers of `policy = "arbiter"` (edge/qos/arbiter.py,
    docs/fleet.md)."""

    max_grants: Annotated[
        int, In(-1, 10_000, "must be -1 (no limit) or 0..10000")
    ] = -1  # at most this many drones hold priority at once (-1: no limit by count)
    max_share: Annotated[float, In(0, 1, "must be in (0, 1]", lo_open=True)] = (
        1.0  # ...and together offer at most this share of uplink_mbps (1: no limit)
    )
    uplink_mbps: Annotated[float, In(0, 1e6, "must be in 0..1000000 Mbit/s")] = (
        0.0  # the cell's uplink the share is of (what the operator contracts)
    )
    min_hold_s: Annotated[float, In(0, 3600, "must be in 0..3600 s")] = (
        3.0  # a grant is revoked for higher latency alone only after this long
    )
    rotate_after_s: Annotated[float, In(0.1, 3600, "must be in 0.1..3600 s")] = (
        30.0  # drones of equal need take turns this often
    )

    def __post_init__(self) -> None:
        _require(
            self.max_share == 1 or self.uplink_mbps > 0,
            "uplink_mbps",
            "is required (> 0) when max_share is below 1",
        )
        _require(self.rotate_after_s >= self.min_hold_s, "rotate_after_s", "must be at least min_hold_s")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class QosConfig:
    """[qos]: how the network is asked for the priority flow (`dynqos edge qos`, docs/qos.md)."""

    backend: Literal["links", "camara", "nef"] = "links"
    hold_down_s: Annotated[float, SECONDS_3600] = (
        5.0  # release a session only after the drone left priority this long
    )
    request_interval_s: Annotated[float, In(0.05, 3600, "must be in 0.05..3600 s")] = (
        1.0  # the drone repeats its request this often
    )
    drone_timeout_s: Annotated[float, SECONDS_3600] = (
        5.0  # the agent treats a drone it has not heard from this long as gone
    )
    agent_timeout_s: Annotated[float, SECONDS_3600] = (
        3.0  # the drone reports "no agent" after this long without a grant
    )
    grant_interval_s: Annotated[float, In(0.05, 3600, "must be in 0.05..3600 s")] = (
        1.0  # the agent repeats each drone's grant this often
    )
    health_interval_s: Annotated[float, SECONDS_3600] = 5.0
    # Who gets priority: every drone that asks, or (arbiter) the neediest within [qos.arbiter]'s budget.
    policy: Literal["grant-all", "arbiter"] = "grant-all"
    # Several agents may run; one holds the sessions, the others stand by (docs/qos.md). replica_id
    # names this one (empty: <host>-<pid>). session_lease_s: the lease the agent's zenoh session
    # announces; an agent that hangs (SIGSTOP, a frozen VM) loses its tokens to the router after it,
    # and a standby takes the sessions over (zenoh's own default is 10 s).
    replica_id: str = ""
    # The edge site of this agent ("" = one site): agents of one site choose their active one among
    # themselves, ask their own operator, and serve the requests a drone on two paths makes for their
    # site (docs/multipath.md)
    site: str = ""
    session_lease_s: Annotated[float, In(0.5, 60, "must be in 0.5..60 s")] = 2.0
    camara: CamaraConfig = field(default_factory=CamaraConfig)
    nef: NefConfig = field(default_factory=NefConfig)
    arbiter: ArbiterConfig = field(default_factory=ArbiterConfig)

    def __post_init__(self) -> None:
        _require(
            self.drone_timeout_s > self.request_interval_s,
            "drone_timeout_s",
            "must exceed request_interval_s",
        )
        _require(
            self.agent_timeout_s > self.grant_interval_s, "agent_timeout_s", "must exceed grant_interval_s"
        )
        _check_replica_id(self.replica_id)
        if self.site:
            _check_name(self.site, "site")
        if self.backend == "camara":
            _require(bool(self.camara.api_root), "camara.api_root", 'is required with backend = "camara"')
        if self.backend == "nef":
            self.nef.required()
        # With links the network prioritises whoever uses the priority port: a revoked grant could not
        # be taken back, so the arbiter's budget would be a wish.
        _require(
            self.policy != "arbiter" or self.backend in ("camara", "nef"),
            "policy",
            'the arbiter needs backend = "camara" or "nef" (a network that enforces its grants)',
        )
