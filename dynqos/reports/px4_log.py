"""What PX4 itself did during a flight, read from its own ULog (pyulog, PX4's reader): its flight modes
(`vehicle_status.nav_state`), its failsafes (`vehicle_status.failsafe`) and the warnings it logged. A
reader of the report sees PX4's side of the flight, not only what the onboard daemon believed.

The pure part (`mode_spans`, `failsafe_onsets`, `flight_figures`) works on plain sequences, so it is tested
without a ULog; `read_ulog` is the thin reader around it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

US_PER_S = 1_000_000
# vehicle_status.nav_state (PX4's msg/VehicleStatus.msg)
NAV_STATES = {
    0: "MANUAL",
    1: "ALTCTL",
    2: "POSCTL",
    3: "AUTO_MISSION",
    4: "AUTO_LOITER",
    5: "AUTO_RTL",
    6: "POSITION_SLOW",
    10: "ACRO",
    12: "DESCEND",
    13: "TERMINATION",
    14: "OFFBOARD",
    15: "STAB",
    17: "AUTO_TAKEOFF",
    18: "AUTO_LAND",
    19: "AUTO_FOLLOW_TARGET",
    20: "AUTO_PRECLAND",
    21: "ORBIT",
    22: "AUTO_VTOL_TAKEOFF",
}
OFFBOARD = 14
ARMED = 2  # vehicle_status.arming_state
DISARMED = " (disarmed)"
WARNING_LEVEL = 4  # ULog's levels are syslog's: 0 emergency .. 4 warning .. 7 debug
MESSAGES_KEPT = 20
# PX4 SITL runs in lockstep with its simulator at about 0.99 of real time (its README): a flight of 30 s
# on the wall clock is about 29.7 s on PX4's.
CLOCK_SHARE = 0.95


def mode_name(nav_state: int) -> str:
    if 23 <= nav_state <= 30:
        return f"EXTERNAL{nav_state - 22}"
    return NAV_STATES.get(nav_state, f"nav_state {nav_state}")


@dataclass(frozen=True, slots=True)
class Span:
    mode: str
    start_s: float  # PX4's boot clock
    end_s: float

    @property
    def duration_s(self) -> float:
        return self.end_s - self.start_s


def mode_spans(
    times_us: Sequence[int], nav_states: Sequence[int], end_us: int, armed: Sequence[bool] | None = None
) -> list[Span]:
    """Each stretch of one flight mode, in order; the last ends with the log (`end_us`). With `armed`, a
    mode PX4 shows while disarmed is named so ("OFFBOARD (disarmed)"): once landed and disarmed PX4 shows
    the mode last chosen again, which is no flight in it."""
    names = [
        mode_name(int(state)) + ("" if armed is None or armed[i] else DISARMED)
        for i, state in enumerate(nav_states)
    ]
    spans: list[Span] = []
    for i, (t, name) in enumerate(zip(times_us, names, strict=True)):
        if i and name == names[i - 1]:
            continue
        if spans:
            spans[-1] = Span(spans[-1].mode, spans[-1].start_s, t / US_PER_S)
        spans.append(Span(name, t / US_PER_S, end_us / US_PER_S))
    return spans


def failsafe_onsets(
    times_us: Sequence[int], failsafe: Sequence[int], nav_states: Sequence[int]
) -> list[dict[str, Any]]:
    """Each time PX4's failsafe flag rose, with the mode PX4 was in when it did."""
    onsets = []
    for i, (t, flag) in enumerate(zip(times_us, failsafe, strict=True)):
        if flag and (i == 0 or not failsafe[i - 1]):
            onsets.append({"t_s": round(t / US_PER_S, 3), "mode": mode_name(int(nav_states[i]))})
    return onsets


def flight_figures(spans: list[Span], onsets: list[dict[str, Any]], flight_s: float) -> dict[str, Any]:
    """The report's figures: the modes in order, the longest OFFBOARD stretch against the recorded flight,
    and the failsafes."""
    offboard = [s.duration_s for s in spans if s.mode == mode_name(OFFBOARD)]
    longest = max(offboard, default=0.0)
    return {
        "modes": [
            {"mode": s.mode, "start_s": round(s.start_s, 3), "duration_s": round(s.duration_s, 3)}
            for s in spans
        ],
        "offboard_s": round(longest, 3),
        "offboard_entries": len(offboard),
        # The recorded flight starts at the first offboard state and the daemon leaves offboard after
        # it: offboard entered once and held about as long (on PX4's clock) is the whole flight.
        "offboard_whole_flight": len(offboard) == 1 and longest >= CLOCK_SHARE * flight_s,
        "failsafes": onsets,
    }


def read_ulog(path: Path, flight_s: float) -> dict[str, Any]:
    """The figures of one ULog: PX4's modes, its failsafes and its warnings (a broken or truncated log is
    said so, not raised: PX4 killed mid-write leaves one)."""
    from pyulog import ULog

    try:
        ulog = ULog(str(path), message_name_filter_list=["vehicle_status"])
    except Exception as exc:  # pyulog raises several kinds on a damaged file
        return {"file": path.name, "error": f"cannot read the ULog: {exc}"}
    status = next((d for d in ulog.data_list if d.name == "vehicle_status"), None)
    if status is None:
        return {"file": path.name, "error": "no vehicle_status in the ULog"}
    times = [int(t) for t in status.data["timestamp"]]
    states = [int(s) for s in status.data["nav_state"]]
    flags = [int(f) for f in status.data["failsafe"]]
    armed = [int(a) == ARMED for a in status.data["arming_state"]]
    spans = mode_spans(times, states, int(ulog.last_timestamp), armed)
    figures = flight_figures(spans, failsafe_onsets(times, flags, states), flight_s)
    warnings = [m for m in ulog.logged_messages if m.log_level <= WARNING_LEVEL]
    seen: dict[str, float] = {}
    for m in warnings:
        seen.setdefault(m.message.strip(), round(m.timestamp / US_PER_S, 3))
    figures["warnings"] = [{"t_s": t, "text": text} for text, t in list(seen.items())[:MESSAGES_KEPT]]
    return {"file": path.name, **figures}


def px4_report(workdir: Path, flight_s: float) -> dict[str, Any]:
    """What PX4 did, from the newest ULog in its working directory (None of it if logging was off)."""
    logs = sorted((workdir / "log").glob("**/*.ulg"))
    if not logs:
        return {"error": f"no ULog in {workdir / 'log'} ([px4] ulog = false?)"}
    return read_ulog(logs[-1], flight_s)
