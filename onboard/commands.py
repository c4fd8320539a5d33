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

Two paths (docs/multipath.md): each edge site's replicas fence within their site (`Command.site`), and
both sites answer every state. The first Command to arrive for a state is taken, whichever site or path
it came by; any later one for a state already answered is a duplicate: dropped and counted, never
applied twice. When the winner's site changes, the step between the two sites' setpoints for that
moment is measured (`steps`), beside the step between two Commands of one site, and bounded: the
setpoint moves at most `site_step_max_mps2` at the change and then towards the new site's plan by that
much per setpoint period (`SiteBlend`), so two sites that disagree never jerk the drone by more.
"""

from __future__ import annotations

import math
from collections import deque
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
    controller_changes: int = 0  # within a site: another replica (or term) took over
    duplicates: int = 0  # for a state already answered (the other path's or the other site's copy)
    site_changes: int = 0  # the winning Command came from another site than the one before
    site_steps_bounded: int = 0  # site changes whose step was above the bound and eased in

    @property
    def rejected(self) -> int:
        return self.wrong_drone + self.stale + self.future + self.expired + self.unknown_state + self.fenced


@dataclass
class SetpointSteps:
    """How far the acceleration setpoint jumps when a new Command takes over (m/s^2, the norm of the
    difference at the moment it arrives): from the same site, and when the winning site changes."""

    same_site_max: float = 0.0
    same_site_sum: float = 0.0
    same_site_count: int = 0
    site_change_max: float = 0.0
    site_change_sum: float = 0.0
    site_change_count: int = 0

    @property
    def site_change_mean(self) -> float:
        return self.site_change_sum / self.site_change_count if self.site_change_count else 0.0

    @property
    def same_site_mean(self) -> float:
        return self.same_site_sum / self.same_site_count if self.same_site_count else 0.0

    def add(self, step: float, site_changed: bool) -> None:
        if site_changed:
            self.site_change_max = max(self.site_change_max, step)
            self.site_change_sum += step
            self.site_change_count += 1
        else:
            self.same_site_max = max(self.same_site_max, step)
            self.same_site_sum += step
            self.same_site_count += 1


@dataclass(frozen=True, slots=True)
class SiteBlend:
    """What is held back of a site change's step: the applied setpoint is the new site's plus `offset`
    at first, so it moves by at most `max_step` at the change; from one setpoint period after it the
    offset shrinks by `max_step` per period, so the setpoint reaches the new plan in
    ceil(|step| / max_step) periods, never moving more than `max_step` per period on its way."""

    offset: tuple[float, float, float]  # m/s^2: (applied before) - (new plan) beyond the bound
    start_ns: int  # the new Command's arrival
    max_step: float
    period_ns: int

    @classmethod
    def of(
        cls, before: tuple[float, ...], after: tuple[float, ...], max_step: float, now_ns: int, period_ns: int
    ) -> SiteBlend | None:
        """The blend for a step from `before` to `after`, or None when the step is within the bound."""
        step = math.dist(before, after)
        if step <= max_step:
            return None
        keep = 1.0 - max_step / step
        x, y, z = ((b - a) * keep for b, a in zip(before, after, strict=True))
        return cls((x, y, z), now_ns, max_step, period_ns)

    def offset_at(self, now_ns: int) -> tuple[float, float, float] | None:
        """The offset still applied at `now_ns`, or None once it has faded."""
        norm = math.hypot(*self.offset)
        periods = max(0.0, (now_ns - self.start_ns - self.period_ns) / self.period_ns)
        left = norm - self.max_step * periods
        if left <= 0.0:
            return None
        scale = left / norm
        x, y, z = (o * scale for o in self.offset)
        return (x, y, z)


ANSWERED_MEMORY = 256  # states whose answer is remembered, to know a duplicate from a lost answer


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
    site: str = ""  # the site of the last accepted Command
    steps: SetpointSteps = field(default_factory=SetpointSteps)
    steps_from_seq: int = (
        0  # steps between Commands for states from this one on (the flight's, not the climb's)
    )
    site_step_max_mps2: float = 0.0  # the bound on the step at a change of site (0: none)
    setpoint_period_ns: int = 20_000_000  # the onboard loop's period, over which a bounded step eases in
    blend: SiteBlend | None = None  # the part of the last site change's step still being eased in

    def __post_init__(self) -> None:
        self.rtts = SlidingWindow(self.rtt_window)
        self._new_rtts: list[float] = []
        self._sent: dict[int, int] = {}  # state seq -> stamp, for states still awaiting an answer
        self._answered: deque[int] = deque(maxlen=ANSWERED_MEMORY)  # accepted state seqs, oldest first
        self.sites: dict[str, tuple[int, str]] = {}  # site -> (term, replica) followed there
        self.wins: dict[str, int] = {}  # site -> Commands accepted from it

    def controllers(self) -> tuple[tuple[str, int, str], ...]:
        """(site, term, replica) per named site followed, for State.controllers (none with one site)."""
        return tuple((site, term, replica) for site, (term, replica) in sorted(self.sites.items()) if site)

    def state_sent(self, seq: int, stamp_ns: int) -> None:
        self._sent[seq] = stamp_ns
        if len(self._sent) > 256:  # bounded: forget the oldest unanswered states
            for old in sorted(self._sent)[:-256]:
                del self._sent[old]

    def oldest_unanswered_ms(self, now_ns: int, answered: int | None = None) -> float | None:
        """Age of the oldest state sent after the last answered one (`answered`: the newest State one
        path answered; None: the newest any Command applied answered): a lower bound on the next RTT."""
        if answered is None:
            answered = self.active.state_seq if self.active else -1
        pending = [stamp for seq, stamp in self._sent.items() if seq > answered]
        return (now_ns - min(pending)) / 1e6 if pending else None

    def offer(self, command: Command, arrival_ns: int) -> bool:
        c = self.counters
        if command.uav != self.uav:
            c.wrong_drone += 1
            return False
        held = self.sites.get(command.site)
        if held is not None and (
            command.term < held[0] or (command.term == held[0] and command.replica != held[1])
        ):
            c.fenced += 1
            return False
        if command.state_seq in self._answered:
            c.duplicates += 1
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
        if held is not None and held != (command.term, command.replica):
            c.controller_changes += 1
        self.sites[command.site] = (command.term, command.replica)
        self.term, self.replica = command.term, command.replica
        if self.last_valid_ns is not None:
            self.longest_gap_ns = max(self.longest_gap_ns, arrival_ns - self.last_valid_ns)
        self._step(command, arrival_ns)
        self._answered.append(command.state_seq)
        self.site = command.site
        self.wins[command.site] = self.wins.get(command.site, 0) + 1
        self.active = command
        self.last_valid_ns = arrival_ns
        c.accepted += 1
        return True

    def _step(self, command: Command, arrival_ns: int) -> None:
        """Measure the step `command` makes of the setpoint flown until now and, at a change of site,
        bound it (an offset eased out, `SiteBlend`)."""
        changed = self.active is not None and command.site != self.site
        self.counters.site_changes += changed
        before = self.setpoint(arrival_ns)  # as flown: with what is left of an earlier blend
        after = _setpoint_of(command, arrival_ns)
        if before is None or after is None:
            self.blend = None if changed else self.blend
            return  # nothing flew just before (or the new one does not cover now): no step
        if changed and self.site_step_max_mps2 > 0:
            bound, period = self.site_step_max_mps2, self.setpoint_period_ns
            self.blend = SiteBlend.of(before.accel_mps2, after.accel_mps2, bound, arrival_ns, period)
            self.counters.site_steps_bounded += self.blend is not None
        if self.active is not None and self.active.state_seq >= self.steps_from_seq:
            self.steps.add(math.dist(before.accel_mps2, after.accel_mps2), changed)

    def take_new_rtts(self) -> list[float]:
        out, self._new_rtts = self._new_rtts, []
        return out

    def setpoint(self, now_ns: int) -> Setpoint | None:
        """The active command's setpoint for now (with what is left of a site change's blend), or None
        when its horizon has run out."""
        setpoint = None if self.active is None else _setpoint_of(self.active, now_ns)
        offset = None if setpoint is None or self.blend is None else self.blend.offset_at(now_ns)
        if setpoint is None or offset is None:
            return setpoint
        x, y, z = (a + o for a, o in zip(setpoint.accel_mps2, offset, strict=True))
        return Setpoint((x, y, z), setpoint.yaw_rad, setpoint.index)

    def watchdog_expired(self, now_ns: int) -> bool:
        return (
            self.last_valid_ns is None
            or now_ns - self.last_valid_ns > self.watchdog_ns
            or self.setpoint(now_ns) is None
        )

    def rtt_estimate_ms(self) -> float:
        mean = self.rtts.mean()
        return 0.0 if mean is None else mean


def _setpoint_of(command: Command, now_ns: int) -> Setpoint | None:
    """`command`'s setpoint for now, or None outside its horizon."""
    if now_ns < command.state_stamp_ns:
        return None
    index = int((now_ns - command.state_stamp_ns) // round(command.dt_s * 1e9))
    if index >= len(command.accel_mps2):
        return None
    return Setpoint(command.accel_mps2[index], command.yaw_rad[index], index)
