"""The take-off as pure logic on the onboard clock: which step comes next, when it has waited long
enough, and when the drone may hand its setpoints to the edge.

Tell the FC the take-off altitude (`MIS_TAKEOFF_ALT`, as MAVSDK does: PX4 reads MAV_CMD_NAV_TAKEOFF's
altitude as metres above sea level, so the command goes out without one), arm, take off, wait until the
FC reports the altitude (within `ALTITUDE_TOLERANCE_M`, at most `CLIMB_TIMEOUT_S`), stream a few hold
setpoints (PX4 refuses offboard mode without a setpoint stream), enter offboard. The shell
(onboard/daemon.py) asks `next` what to do, does it on the FC link and reports the FC's answer with
`answered`. An FC that refuses to arm is asked again every `ARM_RETRY_S` for `ARM_WINDOW_S` (PX4 refuses
until its estimator has aligned, a few seconds after boot, and says why in STATUSTEXT); any other
refusal, or an FC that disarms during the climb, ends the sequence with the reason a person needs. A
command that gets no answer is sent again, its `confirmation` counting the retransmissions, as MAVLink's
command protocol asks (a datagram lost on a busy link is not a refusal), up to `COMMAND_ATTEMPTS` in
all; an FC that never confirms the take-off altitude takes off to its own. Tested tick by tick in
tests/test_takeoff.py.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from dynqos.onboard.fc import FcState

NS_PER_S = 1_000_000_000
ALTITUDE_TOLERANCE_M = 0.15  # the climb is done within this of the take-off altitude
CLIMB_TIMEOUT_S = 30.0  # a climb that takes longer goes on in offboard from wherever the drone is
PRIME_SETPOINTS = 10  # hold setpoints streamed before asking for offboard
PRIME_PERIOD_S = 0.02  # their rate: 50 Hz, the setpoint rate
POLL_S = 0.05  # how often the climb and the FC's first position are looked at
COMMAND_ATTEMPTS = 5  # a command with no answer is sent this many times in all before it is a failure
ARM_RETRY_S = 1.0  # a refused arming is asked for again after this long
ARM_WINDOW_S = 20.0  # ... until this long after the first refusal
DISARM_GRACE_S = 2.0  # an FC that reports itself disarmed this long after the take-off was accepted


NO_ALTITUDE = "the flight controller never confirmed the take-off altitude; it climbs to its own"


class Do(enum.Enum):
    WAIT = "wait"  # nothing to send now; ask again after `wait_s`
    TAKEOFF_ALTITUDE = "set the take-off altitude"
    ARM = "arm"
    TAKE_OFF = "take off"
    HOLD_SETPOINT = "hold setpoint"  # send a position setpoint at `hold`
    OFFBOARD = "offboard"
    DONE = "done"  # airborne in offboard mode: offload
    FAILED = "failed"  # `reason` says why; stay on the ground, streaming only


@dataclass(frozen=True, slots=True)
class Step:
    do: Do
    wait_s: float = 0.0
    hold: FcState | None = None  # the state to hold at (HOLD_SETPOINT)
    reason: str = ""
    confirmation: int = 0  # a command's retransmissions so far (MAVLink COMMAND_LONG.confirmation)


class TakeoffSequencer:
    def __init__(self, altitude_m: float, fc_timeout_s: float, start_ns: int) -> None:
        self.altitude_m = altitude_m
        self._fc_deadline_ns = start_ns + round(fc_timeout_s * NS_PER_S)
        self._climb_deadline_ns: int | None = None
        self._primed = 0
        self._hold: FcState | None = None
        self._asked: Do | None = None  # the command waiting for `answered`
        self._unanswered: dict[Do, int] = {}  # sends of a command that got no answer
        self._done: set[Do] = set()
        self._arm_refused_ns: int | None = None  # the first refusal to arm
        self._arm_retry_ns = 0  # no arming asked for before this
        self._takeoff_ns: int | None = None  # when the take-off was accepted
        self.refusals: list[str] = []  # what the FC refused, with its answer, for the log
        self.failed = ""
        self._now_ns = start_ns

    def next(self, now_ns: int, fc: FcState | None, fc_heard: bool, armed: bool | None = None) -> Step:
        """What to do now, given the FC's latest state, whether its heartbeat has been heard and whether
        it says it is armed (None: not known)."""
        self._now_ns = now_ns
        if self.failed:
            return Step(Do.FAILED, reason=self.failed)
        if Do.ARM not in self._done:
            return self._to_arm(now_ns, fc, fc_heard)
        if Do.TAKE_OFF not in self._done:
            return self._ask(Do.TAKE_OFF)
        if self._hold is None:
            climbing = self._climb(now_ns, fc, armed)
            if climbing is not None:
                return climbing
        if self._primed < PRIME_SETPOINTS:
            self._primed += 1
            return Step(Do.HOLD_SETPOINT, PRIME_PERIOD_S, hold=self._hold)
        if Do.OFFBOARD not in self._done:
            return self._ask(Do.OFFBOARD)
        return Step(Do.DONE, hold=self._hold)

    def _to_arm(self, now_ns: int, fc: FcState | None, fc_heard: bool) -> Step:
        """Until armed: wait for the FC, tell it the take-off altitude, arm (again after a refusal)."""
        if not (fc_heard and fc is not None):
            if now_ns >= self._fc_deadline_ns:
                return self._fail("no heartbeat and position from the flight controller")
            return Step(Do.WAIT, POLL_S)
        if Do.TAKEOFF_ALTITUDE not in self._done:
            return self._ask(Do.TAKEOFF_ALTITUDE)
        if now_ns < self._arm_retry_ns:
            return Step(Do.WAIT, (self._arm_retry_ns - now_ns) / NS_PER_S)
        return self._ask(Do.ARM)

    def _climb(self, now_ns: int, fc: FcState | None, armed: bool | None) -> Step | None:
        """During the climb: a step to take, or None once it is over (the hold is where it ended)."""
        if self._takeoff_ns is None:
            self._takeoff_ns = now_ns
        if armed is False and now_ns - self._takeoff_ns >= DISARM_GRACE_S * NS_PER_S:
            return self._fail("the flight controller disarmed during the climb")
        if self._climb_deadline_ns is None:
            self._climb_deadline_ns = now_ns + round(CLIMB_TIMEOUT_S * NS_PER_S)
        climbed = fc is not None and -fc.pos_m[2] >= self.altitude_m - ALTITUDE_TOLERANCE_M
        if not climbed and now_ns < self._climb_deadline_ns:
            return Step(Do.WAIT, POLL_S)
        if fc is None:
            return self._fail("the flight controller's position went missing during the climb")
        self._hold = fc
        return None

    def answered(self, result: int | None) -> None:
        """The FC's answer to the command `next` asked for (MAV_RESULT; None: no answer in time)."""
        asked, self._asked = self._asked, None
        if asked is None:
            return
        if result is not None and result != 0:
            self.refusals.append(f"the flight controller answered {result} to '{asked.value}'")
        if result == 0:
            self._done.add(asked)
        elif result is None and self._unanswered.get(asked, 0) + 1 < COMMAND_ATTEMPTS:
            self._unanswered[asked] = self._unanswered.get(asked, 0) + 1  # sent again by the next `next`
        elif asked is Do.TAKEOFF_ALTITUDE:
            self._done.add(asked)  # an FC without MIS_TAKEOFF_ALT takes off to its own altitude
            self.refusals.append(NO_ALTITUDE)
        elif asked is Do.ARM and result is not None and self._arm_window_open():
            self._arm_retry_ns = self._now_ns + round(ARM_RETRY_S * NS_PER_S)
        else:
            refusal = "refused offboard mode" if asked is Do.OFFBOARD else f"refused to {asked.value}"
            why = f"did not answer {COMMAND_ATTEMPTS} times" if result is None else f"answered {result}"
            self.failed = f"the flight controller {refusal} ({why})"

    def _arm_window_open(self) -> bool:
        if self._arm_refused_ns is None:
            self._arm_refused_ns = self._now_ns
        return self._now_ns - self._arm_refused_ns < ARM_WINDOW_S * NS_PER_S

    def _ask(self, do: Do) -> Step:
        self._asked = do
        return Step(do, confirmation=self._unanswered.get(do, 0))

    def _fail(self, reason: str) -> Step:
        self.failed = reason
        return Step(Do.FAILED, reason=reason)


class ExitAction(enum.Enum):
    NOTHING = "nothing"  # never offloaded: the FC keeps what it does
    HOLD = "hold"  # the FC holds position (AUTO.LOITER)
    LAND = "land"


def on_exit(offloading: bool, on_exit_setting: str) -> ExitAction:
    """What the drone asks of its FC when the daemon stops (`[onboard] on_exit`): only a drone that was
    flying from the edge hands the FC a mode; one on the ground or still taking off is left alone."""
    if not offloading:
        return ExitAction.NOTHING
    return ExitAction.LAND if on_exit_setting == "land" else ExitAction.HOLD
