"""Profiles: one set of scenario and supervisor settings applied to every scenario of a run, so the
same experiment can be flown with the paper's parameters and with dynqos's own, side by side.

A profile is a TOML file (`dynqos/profiles/*.toml`, or a path): a `[profile]` table with its name and
description, an optional `[scenario]` table of scenario fields and an optional `[supervisor]` table of
`[supervisor]` settings. Each file says why its values are what they are.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

from dynqos.common.config import SupervisorConfig, build
from dynqos.common.errors import ConfigError
from dynqos.plan.scenario import Scenario

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_PROFILE = "dynqos"


@dataclass(frozen=True, slots=True, kw_only=True)
class ProfileInfo:
    name: str
    description: str = ""


@dataclass(frozen=True, slots=True, kw_only=True)
class Profile:
    name: str
    description: str
    scenario: dict[str, Any] = field(default_factory=dict)  # scenario fields it sets, converted on load
    supervisor: dict[str, Any] = field(default_factory=dict)  # [supervisor] settings it sets, converted

    def apply(self, scenario: Scenario) -> Scenario:
        """The scenario under this profile: the fields and supervisor settings the profile names are
        replaced; everything else, a scenario's own [scenario.supervisor] included, stays."""
        supervisor = replace(scenario.supervisor, **self.supervisor)
        return replace(scenario, **self.scenario, supervisor=supervisor, profile=self.name)


def builtin_profiles() -> list[str]:
    files = resources.files("dynqos") / "profiles"
    return sorted(p.name.removesuffix(".toml") for p in files.iterdir() if p.name.endswith(".toml"))


def load_profile(name_or_path: str) -> Profile:
    """A built-in profile by name, or a profile file by path."""
    if name_or_path.endswith(".toml") or "/" in name_or_path:
        file = Path(name_or_path)
        if not file.is_file():
            raise ConfigError("--profile", "profile file not found", source=name_or_path)
        return _parse(file.read_text(encoding="utf-8"), name_or_path)
    path = resources.files("dynqos") / "profiles" / f"{name_or_path}.toml"
    if not path.is_file():
        known = ", ".join(builtin_profiles())
        raise ConfigError("--profile", f"unknown profile {name_or_path!r} (known: {known}, or a file path)")
    return _parse(path.read_text(encoding="utf-8"), name_or_path)


def _parse(text: str, source: str) -> Profile:
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("", f"cannot read profile ({exc})", source=source) from None
    unknown = set(table) - {"profile", "scenario", "supervisor"}
    if unknown or not isinstance(table.get("profile"), dict):
        reason = "a profile file has a [profile] table and optional [scenario] and [supervisor] tables"
        raise ConfigError(", ".join(sorted(unknown)) or "profile", reason, source=source)
    try:
        info = build(ProfileInfo, table["profile"], "profile")
        scenario = dict(table.get("scenario", {}))
        if "name" in scenario or "faults" in scenario:
            raise ConfigError(
                "scenario.name", "a profile changes how scenarios fly, not their names or faults"
            )
        supervisor = dict(table.get("supervisor", {}))
        # Every key and value checked (and converted: arrays to tuples) now, not when a run starts.
        checked = build(Scenario, {"name": "check", **scenario}, "scenario")
        settings = build(SupervisorConfig, supervisor, "supervisor")
    except ConfigError as exc:
        raise exc.with_source(source) from None
    return Profile(
        name=info.name,
        description=info.description,
        scenario={k: getattr(checked, k) for k in scenario},
        supervisor={k: getattr(settings, k) for k in supervisor},
    )
