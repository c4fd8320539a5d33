"""The take-off as pure logic on the onboard clock: which step comes next, when it has waited long
enough, and when the drone may hand its setpoints to the edge.

Tell the FC the take-off altitude (`MIS_TAKEOFF_ALT`, as MAVSDK does: PX4 reads MAV_CMD_NAV_TAKEOFF's
altitude as metres above sea level, so the command goes out without one), arm, take off, wait until the
FC reports the altitude (within `ALTITUDE_TOLERANCE_M`, at most `CLIMB_TIMEOUT_S`), stream a few hold
setpoints (PX4 refuses offboard mode without a setpoint stream), enter offboard. The shell
(onboard/daemon.py) asks `next` what to do, does it on the FC link and reports the FC's answer with
`answered`. The phases and what moves each one on are one table, `TRANSITIONS`. An FC that refuses to
arm is asked again every `ARM_RETRY_S` for `ARM_WINDOW_S` (PX4 refuses until its estimator has aligned,
a few seconds after boot, and says why in STATUSTEXT); any other refusal, or an FC that disarms during
the climb, ends the sequence with the reason a person needs. A command that gets no answer is sent
again, its `confirmation` counting the retransmissions, as MAVLink's command protocol asks (a datagram
lost on a busy link is not a refusal), up to `COMMAND_ATTEMPTS` in all; an FC that never confirms the
take-off altitude takes off to its own. Tested tick by tick and transition by transition in
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


class Phase(enum.Enum):
    WAIT_FC = "waiting for the flight controller"
    ALTITUDE = "setting the take-off altitude"
    ARM = "arming"
    ARM_AGAIN = "waiting to ask for arming again"
    TAKE_OFF = "taking off"
    CLIMB = "climbing"
    PRIME = "streaming hold setpoints"
    OFFBOARD = "entering offboard"
    DONE = "in offboard"
    FAILED = "failed"


class Event(enum.Enum):
    """What moves the take-off on: each is a guard over the FC's state and answers and the clock."""

    FC_HEARD = "the FC's heartbeat and a position are heard"
    FC_SILENT = "neither heard by the FC timeout"
    ACCEPTED = "the FC accepted the command"
    REFUSED = "the FC refused the command"
    REFUSED_EARLY = "the FC refused to arm, within ARM_WINDOW_S of its first refusal"
    UNANSWERED = "no answer to COMMAND_ATTEMPTS sends"
    RETRY_DUE = "ARM_RETRY_S since the refusal"
    CLIMBED = "within ALTITUDE_TOLERANCE_M of the take-off altitude"
    CLIMB_TIMEOUT = "CLIMB_TIMEOUT_S into the climb, the position known"
    POSITION_LOST = "CLIMB_TIMEOUT_S into the climb, no position"
    DISARMED = "the FC reports itself disarmed DISARM_GRACE_S into the climb"
    PRIMED = "PRIME_SETPOINTS hold setpoints sent"


# Every transition of the take-off; a (phase, event) pair not here cannot happen. An enum and a table,
# not a state-machine library: the take-off is part of the drone's pure core (no dependency the onboard
# install would carry for twenty rows), and the table is data that a test walks row by row.
TRANSITIONS: dict[tuple[Phase, Event], Phase] = {
    (Phase.WAIT_FC, Event.FC_HEARD): Phase.ALTITUDE,
    (Phase.WAIT_FC, Event.FC_SILENT): Phase.FAILED,
    (Phase.ALTITUDE, Event.ACCEPTED): Phase.ARM,
    (Phase.ALTITUDE, Event.REFUSED): Phase.ARM,  # an FC without MIS_TAKEOFF_ALT climbs to its own
    (Phase.ALTITUDE, Event.UNANSWERED): Phase.ARM,
    (Phase.ALTITUDE, Event.FC_SILENT): Phase.FAILED,
    (Phase.ARM, Event.ACCEPTED): Phase.TAKE_OFF,
    (Phase.ARM, Event.REFUSED_EARLY): Phase.ARM_AGAIN,  # PX4's estimator is still aligning
    (Phase.ARM, Event.REFUSED): Phase.FAILED,
    (Phase.ARM, Event.UNANSWERED): Phase.FAILED,
    (Phase.ARM, Event.FC_SILENT): Phase.FAILED,
    (Phase.ARM_AGAIN, Event.RETRY_DUE): Phase.ARM,
    (Phase.ARM_AGAIN, Event.FC_SILENT): Phase.FAILED,
    (Phase.TAKE_OFF, Event.ACCEPTED): Phase.CLIMB,
    (Phase.TAKE_OFF, Event.REFUSED): Phase.FAILED,
    (Phase.TAKE_OFF, Event.UNANSWERED): Phase.FAILED,
    (Phase.CLIMB, Event.CLIMBED): Phase.PRIME,
    (Phase.CLIMB, Event.CLIMB_TIMEOUT): Phase.PRIME,
    (Phase.CLIMB, Event.POSITION_LOST): Phase.FAILED,
    (Phase.CLIMB, Event.DISARMED): Phase.FAILED,
    (Phase.PRIME, Event.PRIMED): Phase.OFFBOARD,
    (Phase.OFFBOARD, Event.ACCEPTED): Phase.DONE,
    (Phase.OFFBOARD, Event.REFUSED): Phase.FAILED,
    (Phase.OFFBOARD, Event.UNANSWERED): Phase.FAILED,
}
COMMANDS = {
    Phase.ALTITUDE: Do.TAKEOFF_ALTITUDE,
    Phase.ARM: Do.ARM,
    Phase.TAKE_OFF: Do.TAKE_OFF,
    Phase.OFFBOARD: Do.OFFBOARD,
}
NEEDS_FC = (Phase.WAIT_FC, Phase.ALTITUDE, Phase.ARM, Phase.ARM_AGAIN)  # before arming: the FC must be heard


class TakeoffSequencer:
    def __init__(self, altitude_m: float, fc_timeout_s: float, start_ns: int) -> None:
        self.altitude_m = altitude_m
        self.phase = Phase.WAIT_FC
        self._fc_deadline_ns = start_ns + round(fc_timeout_s * NS_PER_S)
        self._climb_start_ns: int | None = None  # the first look at the climb
        self._primed = 0
        self._hold: FcState | None = None
        self._asked: Do | None = None  # the command waiting for `answered`
        self._unanswered: dict[Do, int] = {}  # sends of a command that got no answer
        self._arm_refused_ns: int | None = None  # the first refusal to arm
        self._arm_retry_ns = 0  # no arming asked for before this
        self.refusals: list[str] = []  # what the FC refused, with its answer, for the log
        self.failed = ""
        self._answer = ""  # the FC's last refusal, for the failure's reason
        self._now_ns = start_ns

    def next(self, now_ns: int, fc: FcState | None, fc_heard: bool, armed: bool | None = None) -> Step:
        """What to do now, given the FC's latest state, whether its heartbeat has been heard and whether
        it says it is armed (None: not known)."""
        self._now_ns = now_ns
        heard = fc_heard and fc is not None
        while (event := self._guard(now_ns, fc, heard, armed)) is not None:
            self._go(event)
        if self.phase in NEEDS_FC and not heard:
            return Step(Do.WAIT, POLL_S)
        return self._step(now_ns)

    def _guard(self, now_ns: int, fc: FcState | None, heard: bool, armed: bool | None) -> Event | None:
        """The event the phase's guards see now, if any."""
        phase = self.phase
        if phase in NEEDS_FC and not heard:
            return Event.FC_SILENT if now_ns >= self._fc_deadline_ns else None
        if phase is Phase.WAIT_FC:
            return Event.FC_HEARD
        if phase is Phase.ARM_AGAIN:
            return Event.RETRY_DUE if now_ns >= self._arm_retry_ns else None
        if phase is Phase.CLIMB:
            return self._climb(now_ns, fc, armed)
        if phase is Phase.PRIME:
            return Event.PRIMED if self._primed >= PRIME_SETPOINTS else None
        return None

    def _climb(self, now_ns: int, fc: FcState | None, armed: bool | None) -> Event | None:
        if self._climb_start_ns is None:
            self._climb_start_ns = now_ns
        into = now_ns - self._climb_start_ns
        if armed is False and into >= DISARM_GRACE_S * NS_PER_S:
            return Event.DISARMED
        climbed = fc is not None and -fc.pos_m[2] >= self.altitude_m - ALTITUDE_TOLERANCE_M
        if not climbed and into < CLIMB_TIMEOUT_S * NS_PER_S:
            return None
        self._hold = fc  # where the climb ended: the hold setpoints and the edge's start
        return Event.POSITION_LOST if fc is None else Event.CLIMBED if climbed else Event.CLIMB_TIMEOUT

    def _go(self, event: Event) -> None:
        target = TRANSITIONS[(self.phase, event)]
        if target is Phase.FAILED:
            self.failed = self._failure(event)
        self.phase = target

    def _failure(self, event: Event) -> str:
        if event is Event.FC_SILENT:
            return "no heartbeat and position from the flight controller"
        if event is Event.DISARMED:
            return "the flight controller disarmed during the climb"
        if event is Event.POSITION_LOST:
            return "the flight controller's position went missing during the climb"
        asked = COMMANDS[self.phase]
        refusal = "refused offboard mode" if asked is Do.OFFBOARD else f"refused to {asked.value}"
        why = f"did not answer {COMMAND_ATTEMPTS} times" if event is Event.UNANSWERED else self._answer
        return f"the flight controller {refusal} ({why})"

    def _step(self, now_ns: int) -> Step:
        phase = self.phase
        if phase in COMMANDS:
            do = self._asked = COMMANDS[phase]
            return Step(do, confirmation=self._unanswered.get(do, 0))
        if phase is Phase.ARM_AGAIN:
            return Step(Do.WAIT, (self._arm_retry_ns - now_ns) / NS_PER_S)
        if phase is Phase.PRIME:
            self._primed += 1
            return Step(Do.HOLD_SETPOINT, PRIME_PERIOD_S, hold=self._hold)
        if phase is Phase.DONE:
            return Step(Do.DONE, hold=self._hold)
        if phase is Phase.FAILED:
            return Step(Do.FAILED, reason=self.failed)
        return Step(Do.WAIT, POLL_S)  # the climb

    def answered(self, result: int | None) -> None:
        """The FC's answer to the command `next` asked for (MAV_RESULT; None: no answer in time)."""
        asked, self._asked = self._asked, None
        if asked is None or COMMANDS.get(self.phase) is not asked:
            return
        if result is None and self._unanswered.get(asked, 0) + 1 < COMMAND_ATTEMPTS:
            self._unanswered[asked] = self._unanswered.get(asked, 0) + 1  # sent again by the next `next`
            return
        if result is not None and result != 0:
            self.refusals.append(f"the flight controller answered {result} to '{asked.value}'")
        self._answer = f"answered {result}"
        if self.phase is Phase.ALTITUDE and result != 0:
            self.refusals.append(NO_ALTITUDE)
        self._go(self._answer_event(asked, result))

    def _answer_event(self, asked: Do, result: int | None) -> Event:
        if result == 0:
            return Event.ACCEPTED
        if result is None:
            return Event.UNANSWERED
        if asked is Do.ARM:
            if self._arm_refused_ns is None:
                self._arm_refused_ns = self._now_ns
            if self._now_ns - self._arm_refused_ns < ARM_WINDOW_S * NS_PER_S:
                self._arm_retry_ns = self._now_ns + round(ARM_RETRY_S * NS_PER_S)
                return Event.REFUSED_EARLY
        return Event.REFUSED


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
