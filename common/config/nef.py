"""[qos.nef]: the QoS agent's settings for a 5G core's NEF (3GPP TS 29.122 AsSessionWithQoS), the API a
private or campus network offers where a public operator offers CAMARA Quality-on-Demand (docs/qos.md,
"Private 5G (NEF)")."""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass, field
from typing import Annotated

from dynqos.common.config.validate import In, _host_port, _loopback, _require, checked
from dynqos.common.errors import ConfigError
from dynqos.common.keys import UAV_ID_PATTERN

# TS 29.571 Gpsi: an MSISDN or an external identifier
_GPSI = re.compile(r"(msisdn-[0-9]{5,15}|extid-[^@]+@[^@]+)")
_REFERENCE = re.compile(r"[A-Za-z0-9_.-]{1,256}")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class NefUeConfig:
    """How the NEF knows a drone's UE: by exactly one of its IPv4 address, its IPv6 address or its GPSI."""

    ipv4: str = ""
    ipv6: str = ""
    gpsi: str = ""  # msisdn-<digits> or extid-<id>@<domain>

    def __post_init__(self) -> None:
        _require(
            sum(bool(v) for v in (self.ipv4, self.ipv6, self.gpsi)) == 1,
            "ue",
            "name the UE by exactly one of ipv4, ipv6, gpsi",
        )
        for key, kind in (("ipv4", ipaddress.IPv4Address), ("ipv6", ipaddress.IPv6Address)):
            value = getattr(self, key)
            if value:
                try:
                    kind(value)
                except ValueError:
                    raise ConfigError(key, f"{value!r} is not an {key.upper()} address") from None
        if self.gpsi:
            _require(
                _GPSI.fullmatch(self.gpsi) is not None,
                "gpsi",
                "must be msisdn-<digits> or extid-<id>@<domain>",
            )

    @property
    def address(self) -> str:
        """The UE's end of a flow description: its address, or `assigned` (RFC 6733's keyword for the
        address the network gave it) when the NEF knows it by GPSI."""
        return self.ipv4 or self.ipv6 or "assigned"


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class NefConfig:
    """[qos.nef]: the NEF the agent asks for AsSessionWithQoS subscriptions, as which SCS/AS, for which
    QoS, and where it hears what happens to them."""

    api_root: str = ""  # the NEF's apiRoot, e.g. https://nef.core.example (the API's path is added)
    scs_as_id: str = "dynqos"  # the SCS/AS the NEF knows this agent as (a path segment)
    qos_reference: str = "QOS_E"  # the QoS the core has configured under this name (its PCF maps it)
    alt_qos_references: tuple[str, ...] = ()  # lesser references the core may fall back to, best first
    qos_duration_s: Annotated[int, In(0, 10**7, "must be in 0..10000000 s (0: not given)")] = 0
    # The agent's notification sink: the URL given to the NEF (the agent adds a secret path segment of
    # its own, the sink's only credential: AsSessionWithQoS defines none) and where it listens
    notification_destination: str = ""
    sink_listen: str = ""
    # QoS monitoring (TS 23.501 5.33.3): the network measures the flow's delays and reports them
    qos_monitoring: bool = False
    monitoring_period_s: Annotated[int, In(1, 3600, "must be in 1..3600 s")] = 1
    # A held subscription is read this often (it still exists); its state comes with the notifications
    read_interval_s: Annotated[float, In(0.1, 3600, "must be in 0.1..3600 s")] = 5.0
    retry_after_denied_s: Annotated[float, In(0.1, 3600, "must be in 0.1..3600 s")] = 10.0
    # OAuth2 client credentials, TLS and the time-out of every call, as [qos.camara]'s (optional: the
    # document allows a NEF without them)
    token_url: str = ""
    client_id: str = ""
    client_secret_file: str = ""
    scope: str = ""
    ca_file: str = ""
    tls_cert_file: str = ""
    tls_key_file: str = ""
    timeout_s: Annotated[float, In(0.05, 60, "must be in 0.05..60 s")] = 2.0
    ues: dict[str, NefUeConfig] = field(default_factory=dict)  # drone id -> its UE

    def __post_init__(self) -> None:
        for name in ("api_root", "token_url", "notification_destination"):
            url = getattr(self, name)
            _require(not url or url.startswith(("http://", "https://")), name, "must be an http(s) URL")
            plain_http_ok = not url.startswith("http://") or _loopback(url)
            _require(plain_http_ok, name, "must be https:// (plain http only to 127.0.0.0/8, ::1, localhost)")
        _require(bool(self.scs_as_id) and "/" not in self.scs_as_id, "scs_as_id", "must be a path segment")
        for key, references in (
            ("qos_reference", (self.qos_reference,)),
            ("alt_qos_references", self.alt_qos_references),
        ):
            for reference in references:
                _require(
                    _REFERENCE.fullmatch(reference) is not None, key, "must be 1..256 of A-Z a-z 0-9 _ . -"
                )
        if self.sink_listen:
            _host_port(self.sink_listen, "sink_listen")
        if self.token_url:
            _require(bool(self.client_id), "client_id", "is required with token_url")
            _require(bool(self.client_secret_file), "client_secret_file", "is required with token_url")
        _require(
            bool(self.tls_cert_file) == bool(self.tls_key_file),
            "tls_cert_file",
            "and tls_key_file go together",
        )
        for uav in self.ues:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, f"ues.{uav}", "is not a drone id")

    def required(self) -> None:
        """What backend = "nef" needs on top: the NEF, and a sink it can tell (its events are the only
        news of a subscription's state)."""
        _require(bool(self.api_root), "nef.api_root", 'is required with backend = "nef"')
        _require(
            bool(self.notification_destination and self.sink_listen),
            "nef.notification_destination",
            'and nef.sink_listen are required with backend = "nef" (the NEF tells the state only there)',
        )
