"""The take-off as pure logic on the onboard clock: which step comes next, when it has waited long
enough, and when the drone may hand its setpoints to the edge.

Arm, take off to `[onboard] takeoff_alt_m`, wait until the FC reports the altitude (within
`ALTITUDE_TOLERANCE_M`, at most `CLIMB_TIMEOUT_S`), stream a few hold setpoints (PX4 refuses offboard
mode without a setpoint stream), enter offboard. The shell (onboard/daemon.py) asks `next` what to do,
does it on the FC link and reports the FC's answer with `answered`; each refusal ends the sequence with
the reason a person needs. A command that gets no answer is sent again, its `confirmation` counting the
retransmissions, as MAVLink's command protocol asks (a datagram lost on a busy link is not a refusal),
up to `COMMAND_ATTEMPTS` in all. Tested tick by tick in tests/test_takeoff.py.
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


class Do(enum.Enum):
    WAIT = "wait"  # nothing to send now; ask again after `wait_s`
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
        self.failed = ""

    def next(self, now_ns: int, fc: FcState | None, fc_heard: bool) -> Step:
        """What to do now, given the FC's latest state and whether its heartbeat has been heard."""
        if self.failed:
            return Step(Do.FAILED, reason=self.failed)
        if Do.ARM not in self._done:
            if not (fc_heard and fc is not None):
                if now_ns >= self._fc_deadline_ns:
                    return self._fail("no heartbeat and position from the flight controller")
                return Step(Do.WAIT, POLL_S)
            return self._ask(Do.ARM)
        if Do.TAKE_OFF not in self._done:
            return self._ask(Do.TAKE_OFF)
        if self._hold is None:
            if self._climb_deadline_ns is None:
                self._climb_deadline_ns = now_ns + round(CLIMB_TIMEOUT_S * NS_PER_S)
            climbed = fc is not None and -fc.pos_m[2] >= self.altitude_m - ALTITUDE_TOLERANCE_M
            if not climbed and now_ns < self._climb_deadline_ns:
                return Step(Do.WAIT, POLL_S)
            if fc is None:
                return self._fail("the flight controller's position went missing during the climb")
            self._hold = fc
        if self._primed < PRIME_SETPOINTS:
            self._primed += 1
            return Step(Do.HOLD_SETPOINT, PRIME_PERIOD_S, hold=self._hold)
        if Do.OFFBOARD not in self._done:
            return self._ask(Do.OFFBOARD)
        return Step(Do.DONE, hold=self._hold)

    def answered(self, result: int | None) -> None:
        """The FC's answer to the command `next` asked for (MAV_RESULT; None: no answer in time)."""
        asked, self._asked = self._asked, None
        if asked is None:
            return
        if result == 0:
            self._done.add(asked)
        elif result is None and self._unanswered.get(asked, 0) + 1 < COMMAND_ATTEMPTS:
            self._unanswered[asked] = self._unanswered.get(asked, 0) + 1  # sent again by the next `next`
        else:
            refusal = "refused offboard mode" if asked is Do.OFFBOARD else f"refused to {asked.value}"
            why = f"did not answer {COMMAND_ATTEMPTS} times" if result is None else f"answered {result}"
            self.failed = f"the flight controller {refusal} ({why})"

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
