"""The one small error hierarchy of dynqos.

DynqosError
├── ConfigError      a config file or CLI value is wrong; says file, key path and reason
├── KeyExprError     a drone id or key expression is malformed
├── MessageError     a message field is invalid; names the field
│   └── DecodeError  bytes from the wire could not be decoded into a valid message
└── TransportError   a zenoh session could not be opened or an endpoint is unusable

Every user-facing command turns a DynqosError into one line on stderr and exit code 2.
Safety paths (watchdog, fallback) never raise: they fall back.
"""

from __future__ import annotations


class DynqosError(Exception):
    """Base of every error dynqos raises on purpose."""


class ConfigError(DynqosError):
    def __init__(self, key: str, reason: str, *, source: str | None = None) -> None:
        self.key = key
        self.reason = reason
        self.source = source
        super().__init__(self._text())

    def _text(self) -> str:
        where = f"{self.source}: " if self.source else ""
        key = f"{self.key}: " if self.key else ""
        return f"{where}{key}{self.reason}"

    def with_source(self, source: str) -> ConfigError:
        return ConfigError(self.key, self.reason, source=source)

    def under(self, prefix: str) -> ConfigError:
        key = f"{prefix}.{self.key}" if self.key else prefix
        return ConfigError(key, self.reason, source=self.source)


class KeyExprError(DynqosError, ValueError):
    pass


class MessageError(DynqosError, ValueError):
    def __init__(self, field: str, reason: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}")


class DecodeError(MessageError):
    pass


class TransportError(DynqosError):
    pass
