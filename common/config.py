"""Configuration: TOML files loaded into frozen, typed dataclasses.

Defaults are the paper's values (mu, rho, w, N, risk thresholds, T_mpc) and DESIGN's. A file sets
only what it changes. Unknown keys, wrong types and out-of-range values are rejected with
ConfigError naming the file, the key path and the reason. Config is loaded once in `main()` and
passed down; there are no globals.
"""

from __future__ import annotations

import math
import sys
import types
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from dynqos.common.errors import ConfigError, KeyExprError
from dynqos.common.keys import check_uav_id

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

T = TypeVar("T")


def _require(condition: bool, key: str, reason: str) -> None:
    if not condition:
        raise ConfigError(key, reason)


@dataclass(frozen=True, slots=True, kw_only=True)
class DroneConfig:
    id: str = "uav1"

    def __post_init__(self) -> None:
        try:
            check_uav_id(self.id)
        except KeyExprError as exc:
            raise ConfigError("id", str(exc)) from None


@dataclass(frozen=True, slots=True, kw_only=True)
class ZenohConfig:
    """How sessions reach the edge router. The two flows are two links to two router ports."""

    edge_host: str = "127.0.0.1"
    default_port: int = 7447
    priority_port: int = 7448
    router_listen_host: str = "127.0.0.1"
    max_links: int = 4
    shared_memory: bool = False
    priority_dscp: int = 0xB8
    bulk_sndbuf_bytes: int = 65536
    connect_timeout_s: float = 5.0

    def __post_init__(self) -> None:
        _require(bool(self.edge_host.strip()), "edge_host", "must not be empty")
        _require(bool(self.router_listen_host.strip()), "router_listen_host", "must not be empty")
        for name in ("default_port", "priority_port"):
            _require(1 <= getattr(self, name) <= 65535, name, "must be a TCP port in 1..65535")
        _require(self.default_port != self.priority_port, "priority_port", "must differ from default_port")
        _require(2 <= self.max_links <= 64, "max_links", "must be in 2..64 (two flows need two links)")
        _require(0 <= self.priority_dscp <= 0xFF, "priority_dscp", "must be a TOS byte in 0..255")
        _require(
            self.bulk_sndbuf_bytes == 0 or 4096 <= self.bulk_sndbuf_bytes <= 64 * 1024 * 1024,
            "bulk_sndbuf_bytes",
            "must be 0 (kernel default) or 4096..67108864",
        )
        _require(0.1 <= self.connect_timeout_s <= 600, "connect_timeout_s", "must be in 0.1..600 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class SupervisorConfig:
    """The PFSM's parameters (paper eq. 1-3, DESIGN section 4). Index 0/1/2 = camera/C&C/risk."""

    mode: Literal["deterministic", "stochastic"] = "deterministic"
    seed: int = 0
    tick_hz: float = 20.0
    mu: tuple[float, float, float] = (3.0, 5.0, 5.0)
    rho: tuple[float, float, float] = (61.0, 27.0, 3.0)
    w: tuple[float, float] = (0.35, 0.65)
    window: tuple[int, int] = (10, 50)
    th_lat: float = 0.5
    risk_high_m: float = 3.0
    risk_medium_m: float = 5.0
    risk_a: float = 0.8
    risk_b: float = 0.2
    dwell_s: float = 1.0
    persist_s: float = 0.5
    recover_s: float = 2.0
    recover_backoff: float = 2.0
    recover_max_s: float = 16.0
    rate_factor: float = 0.5
    min_rate_factor: float = 0.25
    rate_step_s: float = 1.0
    watchdog_s: float = 0.15

    def __post_init__(self) -> None:
        _require(0.1 <= self.tick_hz <= 1000, "tick_hz", "must be in 0.1..1000")
        _require(all(m > 0 for m in self.mu), "mu", "slopes must be > 0")
        _require(all(w >= 0 for w in self.w), "w", "weights must be >= 0")
        _require(
            math.isclose(sum(self.w), 1.0, abs_tol=1e-6), "w", f"weights must sum to 1, got {sum(self.w):g}"
        )
        _require(all(1 <= n <= 10_000 for n in self.window), "window", "window sizes must be in 1..10000")
        _require(0.0 < self.th_lat < 1.0, "th_lat", "must be in (0, 1)")
        _require(0.0 < self.risk_high_m < self.risk_medium_m, "risk_medium_m", "must exceed risk_high_m > 0")
        _require(0.0 <= self.risk_a < 1.0, "risk_a", "must be in [0, 1)")
        _require(0.0 < self.risk_b <= 1.0, "risk_b", "must be in (0, 1]")
        for name in ("dwell_s", "persist_s", "recover_s", "rate_step_s"):
            _require(0.0 <= getattr(self, name) <= 600, name, "must be in 0..600 s")
        _require(1.0 <= self.recover_backoff <= 10.0, "recover_backoff", "must be in 1..10 (1 disables)")
        _require(self.recover_max_s >= self.recover_s, "recover_max_s", "must be >= recover_s")
        _require(
            0.0 < self.min_rate_factor <= self.rate_factor <= 1.0,
            "rate_factor",
            "need 0 < min_rate_factor <= rate_factor <= 1",
        )
        _require(0.001 <= self.watchdog_s <= 60, "watchdog_s", "must be in 0.001..60 s")


@dataclass(frozen=True, slots=True, kw_only=True)
class ControlConfig:
    t_mpc_s: float = 0.05
    horizon: int = 20
    setpoint_hz: float = 50.0

    def __post_init__(self) -> None:
        _require(0.001 <= self.t_mpc_s <= 1.0, "t_mpc_s", "must be in 0.001..1 s")
        _require(5 <= self.horizon <= 200, "horizon", "must be in 5..200 steps")
        _require(
            2.0 < self.setpoint_hz <= 1000, "setpoint_hz", "must be above 2 Hz (PX4 offboard) and <= 1000"
        )


@dataclass(frozen=True, slots=True, kw_only=True)
class Config:
    drone: DroneConfig = field(default_factory=DroneConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    control: ControlConfig = field(default_factory=ControlConfig)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, key: str) -> Any:
    origin = get_origin(tp)
    if is_dataclass(tp) and isinstance(tp, type):
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return build(tp, value, key)
    if origin is Literal:
        options = get_args(tp)
        if value not in options:
            raise ConfigError(key, f"{value!r} is not one of {', '.join(map(repr, options))}")
        return value
    if origin in (Union, types.UnionType):
        raise ConfigError(key, "unsupported type")  # pragma: no cover - no optional settings yet
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list):
            raise ConfigError(key, f"expected an array, got {type(value).__name__}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(key, f"expected an array of {len(args)} values, got {len(value)}")
        return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"expected a string, got {value!r}")
        return value
    raise ConfigError(key, f"unsupported setting type {_type_name(tp)}")  # pragma: no cover


def build(cls: type[T], table: dict[str, Any], prefix: str = "") -> T:
    """A dataclass from a TOML table; every error names the full key path."""
    hints = get_type_hints(cls)
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    for name in table:
        if name not in known:
            path = f"{prefix}.{name}" if prefix else name
            raise ConfigError(path, f"unknown key (known: {', '.join(sorted(known))})")
    kwargs = {}
    for name, value in table.items():
        path = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(hints[name], value, path)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        raise exc.under(prefix) if prefix else exc from None


def _parse_override(text: str) -> tuple[list[str], Any]:
    if "=" not in text:
        raise ConfigError("", f"--set {text!r}: expected KEY=VALUE, e.g. supervisor.th_lat=0.6")
    key, raw = text.split("=", 1)
    key = key.strip()
    try:
        value = tomllib.loads(f"v = {raw.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw.strip()  # a bare word is a string
    parts = key.split(".")
    if not all(parts):
        raise ConfigError(key, "--set: empty key part")
    return parts, value


def _merge(table: dict[str, Any], parts: list[str], value: Any) -> None:
    node = table
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(".".join(parts), f"{part} is not a table")
        node = child
    node[parts[-1]] = value


def load_config(path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Load a TOML file (or the defaults when path is None) and apply `--set KEY=VALUE` overrides."""
    table: dict[str, Any] = {}
    source = "<defaults>"
    if path is not None:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError("", "config file not found", source=source) from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError("", f"cannot read config file ({exc})", source=source) from None
        try:
            table = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"not valid TOML ({exc})", source=source) from None
    for text in overrides:
        parts, value = _parse_override(text)
        _merge(table, parts, value)
        if path is None:
            source = "--set"
    try:
        return build(Config, table)
    except ConfigError as exc:
        raise exc.with_source(source) from None


def to_dict(config: Config) -> dict[str, Any]:
    return asdict(config)


def to_toml(config: Config) -> str:
    """The effective config as TOML (what `dynqos config show` prints)."""
    lines: list[str] = []
    for section, values in to_dict(config).items():
        lines.append(f"[{section}]")
        for key, value in values.items():
            lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")  # pragma: no cover
