"""What both sides of the CAMARA Quality-on-Demand API share: the spec's constants and the reading of a
PortsSpec, and the client secret an operator issues.

The QoS agent at the edge (the client) and the emulated operator (the server, with its JSON Schemas) each
need these; they live here so that the client, which runs from the `edge` extra, never imports the
emulator's schema validator (jsonschema, a `demo` extra)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dynqos.common.errors import ConfigError

QOS_STATUS = ("REQUESTED", "AVAILABLE", "UNAVAILABLE")  # SessionInfo.qosStatus
STATUS_INFO = ("DURATION_EXPIRED", "NETWORK_TERMINATED", "DELETE_REQUESTED")  # SessionInfo.statusInfo
EVENT_TYPE = "org.camaraproject.quality-on-demand.v1.qos-status-changed"  # the CloudEvent's type


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
