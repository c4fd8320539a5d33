"""The checks every config section runs on its values: one ConfigError naming the key and the reason.

A range is declared on the field it bounds, as messages declare theirs (common/fields.py):
`duration_s: Annotated[int, In(1, 10**7, "must be in 1..10000000 s")] = 600`. Every section is
`@checked`: its declared ranges are checked at construction, whether the section came from a file or from
code, before its own `__post_init__` checks what relates one key to another."""

from __future__ import annotations

import ipaddress
import math
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar, get_type_hints

from dynqos.common.errors import ConfigError
from dynqos.common.keys import REPLICA_ID_RULE, valid_replica_id

C = TypeVar("C", bound=type)


@dataclass(frozen=True, slots=True)
class In:
    """A value in lo..hi (either end open when said), or, with `each`, every value of a tuple; `why` is
    the reason the error gives (it names the unit and any special value)."""

    lo: float
    hi: float
    why: str
    lo_open: bool = False
    hi_open: bool = False
    each: bool = False

    def holds(self, value: Any) -> bool:
        values = value if self.each else (value,)
        return all(self._holds(v) for v in values)

    def _holds(self, v: float) -> bool:
        if isinstance(v, float) and not math.isfinite(v):
            return False
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below


_DECLARED: dict[type, tuple[tuple[str, In], ...]] = {}


def declared(cls: type) -> tuple[tuple[str, In], ...]:
    """The ranges `cls` declares, by field name (read once per class)."""
    if cls not in _DECLARED:
        found = []
        for name, hint in get_type_hints(cls, include_extras=True).items():
            found += [(name, meta) for meta in getattr(hint, "__metadata__", ()) if isinstance(meta, In)]
        _DECLARED[cls] = tuple(found)
    return _DECLARED[cls]


def checked(cls: C) -> C:
    """Check the declared ranges at construction, before the section's own `__post_init__` (apply it
    under @dataclass, so that the dataclass's __init__ calls it)."""
    own: Callable[[Any], None] | None = getattr(cls, "__post_init__", None)

    def __post_init__(self: Any) -> None:
        for name, rule in declared(type(self)):
            if not rule.holds(getattr(self, name)):
                raise ConfigError(name, rule.why)
        if own is not None:
            own(self)

    cls.__post_init__ = __post_init__  # type: ignore[attr-defined]
    return cls


def _require(condition: bool, key: str, reason: str) -> None:
    if not condition:
        raise ConfigError(key, reason)


def _check_replica_id(replica_id: str) -> None:
    """An edge replica's id (its liveliness token's last chunk); empty: <host>-<pid> at start."""
    rule = f"{REPLICA_ID_RULE} (or leave it empty)"
    _require(replica_id == "" or valid_replica_id(replica_id), "replica_id", rule)


def _check_name(name: str, key: str) -> None:
    """An edge site's or a drone path's name: the replica id's rule (it goes into keys and logs)."""
    _require(valid_replica_id(name), key, REPLICA_ID_RULE)


def _host_port(text: str, key: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    _require(bool(sep and host), key, f"{text!r} is not host:port")
    _require(port.isdigit() and 1 <= int(port) <= 65535, key, f"{text!r}: port must be 1..65535")
    return host.strip("[]"), int(port)


def _loopback(url: str) -> bool:
    host = urllib.parse.urlsplit(url).hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
