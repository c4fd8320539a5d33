"""Configuration: TOML files loaded into frozen, typed dataclasses (the sections live beside this
module; this is the whole config and its loader).

Defaults are the paper's values where it gives them (mu, rho, w, N, risk thresholds, T_mpc) and
dynqos's own choices elsewhere (docs/supervisor.md says which and why). A file sets only what it
changes. Unknown keys, wrong types and out-of-range values are rejected with ConfigError naming the
file, the key path and the reason. Config is loaded once in `main()` and passed down; there are no
globals.
"""

from __future__ import annotations

import math
import re
import sys
import types
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from dynqos.common.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib
from dynqos.common.config.control import (
    ControlConfig,
    DetectorConfig,
    MpcConfig,
    OnboardConfig,
    PlannerConfig,
    Ros2Config,
    SupervisorConfig,
)
from dynqos.common.config.network import (
    CellConfig,
    DroneConfig,
    MetricsConfig,
    VehicleSimConfig,
    ZenohConfig,
)
from dynqos.common.config.planning import FleetPlanConfig
from dynqos.common.config.px4 import Px4Config
from dynqos.common.config.qos import QosConfig
from dynqos.common.config.validate import checked

T = TypeVar("T")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class Config:
    drone: DroneConfig = field(default_factory=DroneConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    cell: CellConfig = field(default_factory=CellConfig)
    vehicle: VehicleSimConfig = field(default_factory=VehicleSimConfig)
    mpc: MpcConfig = field(default_factory=MpcConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)
    onboard: OnboardConfig = field(default_factory=OnboardConfig)
    qos: QosConfig = field(default_factory=QosConfig)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    fleet_plan: FleetPlanConfig = field(default_factory=FleetPlanConfig)
    px4: Px4Config = field(default_factory=Px4Config)

    def __post_init__(self) -> None:
        bearers = {b.name for b in self.cell.bearer_list(self.zenoh, self.drone.id)}
        for i, event in enumerate(self.cell.events):
            if event.kind == "weight" and event.bearer not in bearers:
                raise ConfigError(
                    f"cell.events[{i}].bearer", f"unknown bearer {event.bearer!r} (known: {sorted(bearers)})"
                )
            if event.kind == "coverage_loss" and event.bearer and event.bearer not in bearers:
                raise ConfigError(
                    f"cell.events[{i}].bearer", f"unknown bearer {event.bearer!r} (known: {sorted(bearers)})"
                )


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(tp: Any, value: Any, key: str) -> Any:
    """`value` from TOML as the field type `tp` asks for, or a ConfigError naming `key`."""
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
    if origin is dict:
        value_type = get_args(tp)[1]
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return {str(k): _convert(value_type, v, f"{key}.{k}") for k, v in value.items()}
    if tp is Any:  # a table handed on as it is (a scenario's settings, checked by the Config they build)
        return value
    if origin in (Union, types.UnionType):
        raise ConfigError(key, "unsupported type")  # pragma: no cover - no optional settings yet
    if origin is tuple:
        return _convert_tuple(get_args(tp), value, key)
    return _convert_scalar(tp, value, key)


def _convert_tuple(args: tuple[Any, ...], value: Any, key: str) -> tuple[Any, ...]:
    if not isinstance(value, list):
        raise ConfigError(key, f"expected an array, got {type(value).__name__}")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_convert(args[0], v, f"{key}[{i}]") for i, v in enumerate(value))
    if len(value) != len(args):
        raise ConfigError(key, f"expected an array of {len(args)} values, got {len(value)}")
    return tuple(_convert(a, v, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))


# TOML's scalars: what each field type accepts and how its error reads
_SCALARS: dict[Any, tuple[Callable[[Any], bool], str]] = {
    bool: (lambda v: isinstance(v, bool), "true or false"),
    int: (lambda v: isinstance(v, int) and not isinstance(v, bool), "an integer"),
    float: (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool), "a number"),
    str: (lambda v: isinstance(v, str), "a string"),
}


def _convert_scalar(tp: Any, value: Any, key: str) -> Any:
    if tp not in _SCALARS:
        raise ConfigError(key, f"unsupported setting type {_type_name(tp)}")  # pragma: no cover
    accepts, expected = _SCALARS[tp]
    if not accepts(value):
        raise ConfigError(key, f"expected {expected}, got {value!r}")
    if tp is float:
        if not math.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return float(value)
    return value


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


ENV_PREFIX = "DYNQOS_"
ENV_NESTING = "__"


def environment_overrides(environ: Mapping[str, str]) -> list[tuple[str, str]]:
    """Settings from the environment, the Kubernetes way: `DYNQOS_<SECTION>__<KEY>=VALUE` (nested as
    pydantic-settings nests them: `DYNQOS_QOS__CAMARA__API_ROOT`), case-insensitive, as
    (variable, `section.key=value`) pairs in a stable order. Variables without `__` (such as a test's
    `DYNQOS_SOAK_S`) are not settings."""
    found = []
    for name in sorted(environ):
        rest = name[len(ENV_PREFIX) :] if name.upper().startswith(ENV_PREFIX) else ""
        if ENV_NESTING in rest:
            path = ".".join(part.lower() for part in rest.split(ENV_NESTING))
            found.append((name, f"{path}={environ[name]}"))
    return found


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    *,
    environment: list[tuple[str, str]] | tuple[tuple[str, str], ...] = (),
) -> Config:
    """Load a TOML file (or the defaults when path is None), then apply `environment` (from
    `environment_overrides`) and then the `--set KEY=VALUE` overrides: the later wins."""
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
    by_key: dict[str, str] = {}  # setting -> the variable or option that set it last
    for variable, text in environment:
        parts, value = _parse_override(text)
        _merge(table, parts, value)
        by_key[".".join(parts)] = f"environment variable {variable}"
    for text in overrides:
        parts, value = _parse_override(text)
        _merge(table, parts, value)
        by_key[".".join(parts)] = "--set"
    try:
        return build(Config, table)
    except ConfigError as exc:
        named = [who for key, who in by_key.items() if _related(exc.key, key)]
        raise exc.with_source(named[-1] if named else source) from None


def _related(a: str, b: str) -> bool:
    """One key path is the other or lies inside it (`qos` and `qos.camara.api_root`)."""
    return a == b or a.startswith(b + ".") or b.startswith(a + ".")


def overlaid(config: Config, table: Mapping[str, Any]) -> Config:
    """`config` with the settings of `table` (nested by section, as a file writes them) over it, checked
    as a file's are; a ConfigError names the key inside `table`."""
    merged = tomllib.loads(to_toml(config))

    def merge(into: dict[str, Any], settings: Mapping[str, Any], path: str) -> None:
        for key, value in settings.items():
            if isinstance(value, Mapping) and isinstance(into.get(key), dict):
                merge(into[key], value, f"{path}{key}.")
            else:
                into[key] = value

    merge(merged, table, "")
    return build(Config, merged)


def to_dict(config: Config) -> dict[str, Any]:
    return asdict(config)


def to_toml(config: Config) -> str:
    """The effective config as TOML (what `dynqos config show` prints)."""
    lines: list[str] = []
    for section, values in to_dict(config).items():
        lines.append(f"[{section}]")
        tables = {
            k: v for k, v in values.items() if isinstance(v, (list, tuple)) and v and isinstance(v[0], dict)
        }
        for key, value in values.items():
            if key not in tables:
                lines.append(f"{key} = {_toml_value(value)}")
        lines.append("")
        for key, items in tables.items():
            for item in items:
                lines.append(f"[[{section}.{key}]]")
                lines.extend(f"{k} = {_toml_value(v)}" for k, v in item.items())
                lines.append("")
    return "\n".join(lines)


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else _toml_value(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):  # a nested table, inline
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")  # pragma: no cover
