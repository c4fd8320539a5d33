"""What the operator's QoS Profiles API (CAMARA qos-profiles v1.1.0) says about the profile the agent is
set to ask for, read once before any session: a profile that does not exist or is not ACTIVE is a
setting to fix before flying, not an error to meet at the first create mid-flight; a duration outside
the profile's minDuration..maxDuration is fitted into it (maxDuration bounds a session with all its
extensions, so asking for more only earns a capped session). Pure: the answer is passed in (profiles.py
asks for it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# CAMARA TimeUnitEnum, in seconds
SECONDS_PER_UNIT = {
    "Days": 86400.0,
    "Hours": 3600.0,
    "Minutes": 60.0,
    "Seconds": 1.0,
    "Milliseconds": 1e-3,
    "Microseconds": 1e-6,
    "Nanoseconds": 1e-9,
}


class ProfileError(Exception):
    """The operator's profiles rule out the configured one: a sentence naming why."""


@dataclass(frozen=True, slots=True)
class ProfileFit:
    duration_s: int  # what to ask for per session
    note: str  # what the agent logs: the profile's bounds and whether the duration moved


def duration_s(value: Any) -> float | None:
    """A CAMARA Duration object ({value, unit}) in seconds; None when absent or malformed."""
    if not isinstance(value, dict):
        return None
    amount, unit = value.get("value"), value.get("unit")
    if isinstance(amount, bool) or not isinstance(amount, int) or unit not in SECONDS_PER_UNIT:
        return None
    return amount * SECONDS_PER_UNIT[unit]


def fit(profiles: Any, name: str, wanted_s: int) -> ProfileFit:
    """The duration to ask for under profile `name`, from a retrieve-qos-profiles answer (a list of
    QosProfile objects). Raises ProfileError when the profile is not offered or not ACTIVE."""
    if not isinstance(profiles, list):
        raise ProfileError(f"retrieve-qos-profiles did not answer a list: {str(profiles)[:200]}")
    named = [p for p in profiles if isinstance(p, dict) and p.get("name") == name]
    if not named:
        offered = sorted(str(p.get("name")) for p in profiles if isinstance(p, dict) and p.get("name"))
        raise ProfileError(f"profile {name} is not offered (offered: {', '.join(offered) or 'none'})")
    profile = named[0]
    status = profile.get("status")
    if status != "ACTIVE":
        raise ProfileError(f"profile {name} is {status} (only an ACTIVE profile can start a session)")
    low, high = duration_s(profile.get("minDuration")), duration_s(profile.get("maxDuration"))
    bounds = f"{_s(low)}..{_s(high)} s"
    if high is not None and wanted_s > high:
        if high < 1:
            raise ProfileError(f"profile {name} allows sessions of at most {high:g} s")
        return ProfileFit(
            int(high), f"profile {name} is ACTIVE, {bounds}: asking for {int(high)} s, not {wanted_s}"
        )
    if low is not None and wanted_s < low:
        raised = int(-(-low // 1))  # whole seconds, rounded up into the range
        return ProfileFit(
            raised, f"profile {name} is ACTIVE, {bounds}: asking for {raised} s, not {wanted_s}"
        )
    return ProfileFit(wanted_s, f"profile {name} is ACTIVE, {bounds}: asking for {wanted_s} s")


def _s(value: float | None) -> str:
    return "?" if value is None else f"{value:g}"
