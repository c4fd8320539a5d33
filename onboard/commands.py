"""Commands from the edge on the drone's side: validation, the setpoint for now, RTT and the watchdog. Pure.

A Command is accepted only if it is for this drone, answers a state we sent (its state_seq is newer
than the last accepted one: duplicates, replays and reordering are rejected), its state_stamp_ns is
not in the future and its horizon still covers now. The setpoint for onboard time t is index
floor((t - state_stamp_ns) / dt_s). RTT = arrival - state_stamp - edge_hold (onboard clock only).
The watchdog expires when no valid command has arrived for `watchdog_ns`.

Fencing: a command whose term is below the highest term accepted so far comes from a replica that has
been replaced (a hung or partitioned MPC that came back) and is refused; an equal term from another
replica than the one that holds it is refused too, so two replicas never fly the drone at once
(edge/replicas.py). The term and replica followed go back to the edge in every State.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from dynqos.common.messages import Command
from dynqos.common.stats import SlidingWindow


@dataclass
class CommandCounters:
    accepted: int = 0
    wrong_drone: int = 0
    stale: int = 0
    future: int = 0
    expired: int = 0
    unknown_state: int = 0
    fenced: int = 0  # from a replica with an older term, or a second replica claiming the same term
    controller_changes: int = 0

    @property
    def rejected(self) -> int:
        return self.wrong_drone + self.stale + self.future + self.expired + self.unknown_state + self.fenced


@dataclass(frozen=True, slots=True)
class Setpoint:
    accel_mps2: tuple[float, float, float]
    yaw_rad: float
    index: int


@dataclass
class CommandTracker:
    uav: str
    watchdog_ns: int
    rtt_window: int = 50
    counters: CommandCounters = field(default_factory=CommandCounters)
    active: Command | None = None
    last_valid_ns: int | None = None
    last_rtt_ms: float | None = None
    longest_gap_ns: int = 0  # between two accepted commands
    term: int = 0  # the controller followed: the highest term accepted, and the replica holding it
    replica: str = ""

    def __post_init__(self) -> None:
        self.rtts = SlidingWindow(self.rtt_window)
        self._new_rtts: list[float] = []
        self._sent: dict[int, int] = {}  # state seq -> stamp, for states still awaiting an answer

    def state_sent(self, seq: int, stamp_ns: int) -> None:
        self._sent[seq] = stamp_ns
        if len(self._sent) > 256:  # bounded: forget the oldest unanswered states
            for old in sorted(self._sent)[:-256]:
                del self._sent[old]

    def oldest_unanswered_ms(self, now_ns: int) -> float | None:
        """Age of the oldest state sent after the last answered one: a lower bound on the next RTT."""
        answered = self.active.state_seq if self.active else -1
        pending = [stamp for seq, stamp in self._sent.items() if seq > answered]
        return (now_ns - min(pending)) / 1e6 if pending else None

    def offer(self, command: Command, arrival_ns: int) -> bool:
        c = self.counters
        if command.uav != self.uav:
            c.wrong_drone += 1
            return False
        if command.term < self.term or (
            command.term == self.term and self.active is not None and command.replica != self.replica
        ):
            c.fenced += 1
            return False
        if self.active is not None and command.state_seq <= self.active.state_seq:
            c.stale += 1
            return False
        sent_stamp = self._sent.get(command.state_seq)
        if sent_stamp is None or sent_stamp != command.state_stamp_ns:
            c.unknown_state += 1  # not an answer to a state we sent (or its stamp was altered)
            return False
        if command.state_stamp_ns > arrival_ns:
            c.future += 1
            return False
        horizon_end = command.state_stamp_ns + round(len(command.accel_mps2) * command.dt_s * 1e9)
        if arrival_ns >= horizon_end:
            c.expired += 1
            return False
        rtt_ms = (arrival_ns - command.state_stamp_ns - command.edge_hold_ns) / 1e6
        if rtt_ms >= 0:
            self.rtts.push(rtt_ms)
            self._new_rtts.append(rtt_ms)
            self.last_rtt_ms = rtt_ms
        for seq in [s for s in self._sent if s <= command.state_seq]:
            del self._sent[seq]
        if (command.term, command.replica) != (self.term, self.replica):
            if self.active is not None:
                c.controller_changes += 1
            self.term, self.replica = command.term, command.replica
        if self.last_valid_ns is not None:
            self.longest_gap_ns = max(self.longest_gap_ns, arrival_ns - self.last_valid_ns)
        self.active = command
        self.last_valid_ns = arrival_ns
        c.accepted += 1
        return True

    def take_new_rtts(self) -> list[float]:
        out, self._new_rtts = self._new_rtts, []
        return out

    def setpoint(self, now_ns: int) -> Setpoint | None:
        """The active command's setpoint for now, or None when its horizon has run out."""
        command = self.active
        if command is None or now_ns < command.state_stamp_ns:
            return None
        index = int((now_ns - command.state_stamp_ns) // round(command.dt_s * 1e9))
        if index >= len(command.accel_mps2):
            return None
        return Setpoint(command.accel_mps2[index], command.yaw_rad[index], index)

    def watchdog_expired(self, now_ns: int) -> bool:
        return (
            self.last_valid_ns is None
            or now_ns - self.last_valid_ns > self.watchdog_ns
            or self.setpoint(now_ns) is None
        )

    def rtt_estimate_ms(self) -> float:
        mean = self.rtts.mean()
        return 0.0 if mean is None else mean
