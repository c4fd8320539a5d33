"""What both sides of the CAMARA Quality-on-Demand API share: the spec's constants and the reading of a
PortsSpec, and the client secret an operator issues.

The QoS agent at the edge (the client) and the emulated operator (the server, with its JSON Schemas) each
need these; they live here so that the client, which runs from the `edge` extra, never imports the
emulator's schema validator (jsonschema, a `demo` extra)."""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path
from typing import Any

from dynqos.common.errors import ConfigError

QOS_STATUS = ("REQUESTED", "AVAILABLE", "UNAVAILABLE")  # SessionInfo.qosStatus
STATUS_INFO = ("DURATION_EXPIRED", "NETWORK_TERMINATED", "DELETE_REQUESTED")  # SessionInfo.statusInfo
EVENT_TYPE = "org.camaraproject.quality-on-demand.v1.qos-status-changed"  # the CloudEvent's type
# The scope each call needs (the documents' `security: openId: [...]`), by (method, last path part)
SCOPES = {
    ("POST", "sessions"): "quality-on-demand:sessions:create",
    ("GET", "sessions"): "quality-on-demand:sessions:read",
    ("DELETE", "sessions"): "quality-on-demand:sessions:delete",
    ("POST", "extend"): "quality-on-demand:sessions:update",
    ("POST", "retrieve-sessions"): "quality-on-demand:sessions:retrieve-by-device",
    ("POST", "retrieve-qos-profiles"): "qos-profiles:read",
    ("GET", "qos-profiles"): "qos-profiles:read",
    ("POST", "retrieve"): "predictive-connectivity-data:read",  # Predictive Connectivity Data 0.1.0
    ("POST", "device-qos-bookings"): "qos-booking:device-qos-bookings:create",  # QoS Booking 0.1.0
    ("GET", "device-qos-bookings"): "qos-booking:device-qos-bookings:read",
    ("DELETE", "device-qos-bookings"): "qos-booking:device-qos-bookings:delete",
    ("POST", "retrieve-device-qos-bookings"): "qos-booking:device-qos-bookings:retrieve-by-device",
}
AGENT_SCOPE = " ".join(dict.fromkeys(SCOPES.values()))  # every call the agent makes
JWT_BEARER = "urn:ietf:params:oauth:client-assertion-type:jwt-bearer"  # RFC 7523 client authentication
JWT_BEARER_GRANT = "urn:ietf:params:oauth:grant-type:jwt-bearer"  # RFC 7523 authorization grant


def rfc3339(unix_s: float, timespec: str = "seconds") -> str:
    """A CAMARA date-time: RFC 3339 in UTC, with its zone as Z."""
    return (
        dt.datetime.fromtimestamp(unix_s, dt.timezone.utc).isoformat(timespec=timespec).replace("+00:00", "Z")
    )


def unix_time(text: Any) -> float:
    """An RFC 3339 date-time that has its zone, as Unix seconds; ValueError otherwise."""
    if not isinstance(text, str):
        raise ValueError("a date-time is a string")
    stamp = dt.datetime.fromisoformat(text.replace("Z", "+00:00").replace("z", "+00:00"))
    if stamp.tzinfo is None:
        raise ValueError(f"{text} has no time zone")
    return stamp.timestamp()


def scope_for(method: str, path: str) -> str:
    """The scope a call to `path` (under the API's root) needs."""
    parts = [p for p in path.split("/") if p]
    if len(parts) >= 2 and parts[-2] in ("sessions", "qos-profiles", "device-qos-bookings"):
        parts = parts[:-1]  # /sessions/{id}, /qos-profiles/{name}
    return SCOPES.get((method, parts[-1] if parts else ""), "")


def load_private_key(path: str, setting: str = "qos.camara.client_key_file") -> Any:
    """The PEM private key (RSA or EC P-256) in `path`; a ConfigError naming `setting` when it is not one."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec, rsa

    try:
        key = serialization.load_pem_private_key(Path(path).read_bytes(), password=None)
    except OSError as exc:
        raise ConfigError(setting, f"cannot read {path} ({exc.strerror})") from None
    except (ValueError, TypeError) as exc:
        raise ConfigError(setting, f"{path} is not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, (rsa.RSAPrivateKey, ec.EllipticCurvePrivateKey)):
        raise ConfigError(setting, f"{path}: only RSA and EC (P-256) keys sign client assertions")
    return key


def signing_algorithm(key: Any) -> str:
    """RS256 for an RSA key, ES256 for an EC one (what operators' identity servers accept)."""
    from cryptography.hazmat.primitives.asymmetric import rsa

    return "RS256" if isinstance(key, (rsa.RSAPrivateKey, rsa.RSAPublicKey)) else "ES256"


def ports_named(spec: dict[str, Any] | None) -> set[int]:
    """The ports a PortsSpec names (its `ports` and every port of its `ranges`); empty when absent."""
    spec = spec or {}
    out = set(spec.get("ports") or [])
    for r in spec.get("ranges") or []:
        out.update(range(int(r["from"]), int(r["to"]) + 1))
    return out


def read_secret(path: str, setting: str = "qos.camara.client_secret_file") -> str:
    """The secret in the file at `path` (stripped); "" when no file is configured. An unreadable or empty
    file is a ConfigError naming `setting`: one line at start, never a failed call mid-flight."""
    if not path:
        return ""
    try:
        secret = Path(path).read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ConfigError(setting, f"cannot read {path} ({exc.strerror})") from None
    if not secret:
        raise ConfigError(setting, f"{path} is empty")
    return secret


HEADER_LINE = re.compile(r"([!#$%&'*+.^_`|~0-9A-Za-z-]+):[ \t]*(\S.*?)\s*")  # an HTTP field name, a value


def read_headers(path: str, setting: str = "qos.camara.headers_file") -> dict[str, str]:
    """The `Name: value` lines of the file at `path` (blank lines and # comments skipped); {} when no
    file is configured. Anything else is a ConfigError naming `setting` and the line, never its value."""
    if not path:
        return {}
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigError(setting, f"cannot read {path} ({exc.strerror})") from None
    headers: dict[str, str] = {}
    for number, line in enumerate(lines, start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        match = HEADER_LINE.fullmatch(line)
        if match is None:
            raise ConfigError(setting, f"{path} line {number} is not `Name: value`")
        headers[match.group(1)] = match.group(2)
    if not headers:
        raise ConfigError(setting, f"{path} names no header")
    return headers


def tls_context(ca_file: str, cert_file: str, key_file: str) -> Any:
    """The TLS settings for calls to the operator: its CA (else the system's trust) and our client
    certificate (mutual TLS), or None when none is set. A file that does not load is a ConfigError."""
    if not (ca_file or cert_file):
        return None
    import ssl

    try:
        context = ssl.create_default_context(cafile=ca_file or None)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError("qos.camara.ca_file", f"cannot load {ca_file} ({exc})") from None
    if cert_file:
        try:
            context.load_cert_chain(cert_file, key_file)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(
                "qos.camara.tls_cert_file", f"cannot load {cert_file} with {key_file} ({exc})"
            ) from None
    return context
