"""The checks every config section runs on its values: one ConfigError naming the key and the reason."""

from __future__ import annotations

import re

from dynqos.common.errors import ConfigError


def _require(condition: bool, key: str, reason: str) -> None:
    if not condition:
        raise ConfigError(key, reason)


def _check_replica_id(replica_id: str) -> None:
    """An edge replica's id (its liveliness token's last chunk); empty: <host>-<pid> at start."""
    _require(replica_id == "" or re.fullmatch(r"[A-Za-z0-9_-]{1,64}", replica_id) is not None,
             "replica_id", "use 1 to 64 characters from A-Z a-z 0-9 _ - (or leave it empty)")  # fmt: skip


def _host_port(text: str, key: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    _require(bool(sep and host), key, f"{text!r} is not host:port")
    _require(port.isdigit() and 1 <= int(port) <= 65535, key, f"{text!r}: port must be 1..65535")
    return host.strip("[]"), int(port)
