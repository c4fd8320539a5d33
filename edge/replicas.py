"""Which replica of an edge service flies which drone, and when another takes over. Pure.

Every replica sees the same live set (zenoh liveliness tokens, one per replica) and ranks it per drone
by rendezvous hashing: the first is the drone's primary, the second its standby. When a replica joins or
leaves, only the drones it ranks first or second for move. Whoever serves a drone stamps its commands
with a term; the drone accepts only the highest term it has seen (onboard/commands.py) and reports it
in every State, so two replicas never fly one drone, and a replica that comes back after a hang or a
partition with an old term is ignored and steps down.

A replica takes a drone (with the highest term it has seen + 1) when it is the first-ranked live
replica and the holder is gone, is another replica ranked below it (a join moves the drone back), or
has been silent for `lease_ns` (a hung process keeps its token; its silence does not). Silent means,
by default, that it left a state unanswered that long (a standby then watches the holder's commands);
with `beats`, that its heartbeat stopped that long: a standby then needs none of the holder's
commands, only its beats, one per replica and not per drone (the MPC's case: receiving and decoding
every command it does not send cost a standby most of what serving costs, docs/benchmarks.md).
A replica that was just displaced waits `holdoff_ns` before it takes a drone back by rank alone, so a
replica that flaps does not drag its drones with it; the holder's silence takes it back at once (a
replica that took a drone from a busy peer and then hung is replaced within a lease, not a holdoff).
"""

from __future__ import annotations

import enum
import hashlib
from collections.abc import Iterable
from dataclasses import dataclass

from dynqos.common.keys import check_replica_id, valid_replica_id

MAX_REPLICAS = 256  # a token flood beyond this is ignored (and counted) rather than ranked


def weight(replica: str, uav: str) -> int:
    """Rendezvous weight: stable across processes and machines (unlike hash())."""
    digest = hashlib.blake2b(f"{replica}\x00{uav}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def ranked(uav: str, members: Iterable[str]) -> list[str]:
    """Live replicas, best first for `uav` (ties, impossible in practice, fall to the name)."""
    return sorted(members, key=lambda r: (-weight(r, uav), r))


class Role(str, enum.Enum):
    SERVE = "serve"  # this replica answers the drone's states with its term
    WATCH = "watch"  # standby: keeps a warm controller, watches the holder's lease
    IDLE = "idle"  # neither primary nor standby: nothing to do for this drone


@dataclass
class Seat:
    """One drone as this replica sees it."""

    term: int = 0  # the highest term seen (the drone's own report, commands, our own)
    holder: str | None = None  # who holds `term`, when known
    latest_seq: int = -1  # the newest state seen
    answered_seq: int = -1  # the newest state the holder has answered
    unanswered_since_ns: int | None = None  # when a state newer than `answered_seq` was first seen
    holder_since_ns: int = 0  # when `holder` was first seen holding `term` (its lease counts from then)
    displaced_ns: int | None = None  # when another replica took this drone from us


@dataclass(frozen=True, slots=True)
class Change:
    """A change of this replica's role for one drone, for the log."""

    uav: str
    role: Role
    term: int
    reason: str


@dataclass
class ReplicaCounters:
    takeovers: int = 0
    stepped_down: int = 0
    stale_commands: int = 0  # commands seen with a term below the drone's (a fenced replica)
    members_refused: int = 0  # tokens beyond MAX_REPLICAS or with an invalid name
    own_stalls: int = 0  # turns of our own loop late enough to hold the judging of silence (`on_turn`)


class Assignment:
    def __init__(
        self, me: str, *, lease_ns: int, holdoff_ns: int, drone_arbitrates: bool = True, beats: bool = False
    ) -> None:
        """`drone_arbitrates`: the drone reports whom it follows (the MPC's case), which settles two
        replicas that took the same term; otherwise (the planner's) the better ranked of them keeps it.
        `beats`: a holder is silent when its heartbeat (`on_beat`) stops, not when a state waits."""
        check_replica_id(me)
        self.me = me
        self.lease_ns = lease_ns
        self.holdoff_ns = holdoff_ns
        self.drone_arbitrates = drone_arbitrates
        self.beats = beats
        self.members: set[str] = {me}
        self.seats: dict[str, Seat] = {}
        self.counters = ReplicaCounters()
        self.beat_ns: dict[str, int] = {}  # each other live replica's newest heartbeat
        # Silence is judged against our own loop's time (`on_turn`), held still across a stall of our
        # own until the peers' beats that zenoh's threads held meanwhile have come in.
        self.loop_ns = 0
        self.stall_ns = lease_ns // 5  # a turn this much later than due is a stall of our own
        self.hold_ns = 2 * self.stall_ns  # after which no silence is counted for this long
        self._turn_ns = 0  # our loop's last turn
        self._held_until_ns = 0  # no silence is counted before this (a stall of our own just ended)
        self._orders: dict[str, list[str]] = {}  # `ranked` per drone for the live set (blake2b per member)
        self._rescan = True  # the live set changed since the last tick: every seat is looked at

    # membership -------------------------------------------------------------------------------------
    def join(self, replica: str) -> bool:
        if replica in self.members:
            return False
        if not valid_replica_id(replica) or len(self.members) >= MAX_REPLICAS:
            self.counters.members_refused += 1
            return False
        self.members.add(replica)
        self._orders.clear()
        self._rescan = True
        return True

    def leave(self, replica: str) -> bool:
        if replica == self.me or replica not in self.members:
            return False
        self.members.discard(replica)
        self.beat_ns.pop(replica, None)
        self._orders.clear()
        self._rescan = True
        return True

    def on_beat(self, replica: str, now_ns: int) -> None:
        """A heartbeat (with `beats`): another replica's says it is alive and its loop turns (our own,
        delivered within our session, say nothing about our receiving and are not counted)."""
        if replica != self.me and replica in self.members:
            self.beat_ns[replica] = max(now_ns, self.beat_ns.get(replica, now_ns))

    def on_turn(self, now_ns: int, due_gap_ns: int) -> int:
        """Our loop turned (with `beats`), its last turn having asked for the next within `due_gap_ns`.
        A peer's silence is counted on this loop's time, not on the clock, and not across a stall of
        our own: a process that was descheduled, or whose loop held the GIL, received nothing meanwhile
        either, and right after it the backlog of its peers' beats still waits on zenoh's threads (our
        own beat, sent at once, would come first). So a turn later than due by more than `stall_ns` holds
        the time still for `hold_ns` (twice that) while the backlog comes in. Returns the stall's gap
        (0: none)."""
        gap_ns = now_ns - self._turn_ns if self._turn_ns else 0
        stalled = gap_ns > due_gap_ns + self.stall_ns
        if stalled:
            self._held_until_ns = now_ns + self.hold_ns
            self.counters.own_stalls += 1
        self._turn_ns = max(self._turn_ns, now_ns)
        if now_ns >= self._held_until_ns:
            self.loop_ns = max(self.loop_ns, now_ns)
        return gap_ns if stalled else 0

    def order(self, uav: str) -> list[str]:
        """The live replicas, best first for `uav` (cached until the live set changes)."""
        order = self._orders.get(uav)
        if order is None:
            if len(self._orders) >= 4 * 4096:  # drone ids from the wire: bounded
                self._orders.clear()
            order = self._orders[uav] = ranked(uav, self.members)
        return order

    def role(self, uav: str) -> Role:
        seat = self.seats.get(uav)
        if seat is not None and seat.holder == self.me:
            return Role.SERVE
        return Role.WATCH if self.me in self.order(uav)[:2] else Role.IDLE

    def mine(self, uav: str) -> bool:
        """Whether this replica should receive the drone's messages at all (primary, standby or holder)."""
        return self.role(uav) is not Role.IDLE

    # what the wire tells us --------------------------------------------------------------------------
    def on_state(self, uav: str, seq: int, drone_term: int, drone_holder: str, now_ns: int) -> Change | None:
        """A state from the drone, carrying the term (and its holder) the drone accepts now."""
        seat = self.seats.setdefault(uav, Seat())
        if seq < seat.latest_seq:  # the drone restarted (or states crossed): count from here
            seat.answered_seq = -1
        seat.latest_seq = seq
        change = None
        other_holder = bool(drone_holder) and drone_holder != seat.holder
        if drone_term > seat.term or (drone_term == seat.term and other_holder):
            change = self._new_holder(
                uav,
                seat,
                drone_term,
                drone_holder or None,
                now_ns,
                f"the drone follows {drone_holder or '?'}",
            )
        waiting = seat.holder != self.me and seq > seat.answered_seq and seat.unanswered_since_ns is None
        if waiting and not self.beats:
            seat.unanswered_since_ns = now_ns
        return change or self._maybe_take(uav, seat, now_ns)

    def on_command(self, uav: str, state_seq: int, term: int, replica: str, now_ns: int) -> Change | None:
        """A command some replica (maybe this one) sent to the drone, answering state `state_seq`."""
        seat = self.seats.setdefault(uav, Seat())
        if term < seat.term:
            self.counters.stale_commands += 1
            return None
        change = None
        if term > seat.term or seat.holder is None:
            change = self._new_holder(uav, seat, term, replica, now_ns, f"{replica} holds term {term}")
        elif not self.drone_arbitrates and seat.holder == self.me and replica != self.me:
            order = ranked(uav, self.members | {replica})  # a replica not (yet) live: not cached
            if order.index(replica) < order.index(self.me):  # both took this term: the better ranked keeps it
                change = self._new_holder(
                    uav, seat, term, replica, now_ns, f"{replica} also took term {term}"
                )
        if replica == seat.holder and state_seq > seat.answered_seq:
            seat.answered_seq = state_seq
            # a newer state may still wait: time it from now (later than its arrival: never too early)
            seat.unanswered_since_ns = None if state_seq >= seat.latest_seq else now_ns
        return change

    def _new_holder(
        self, uav: str, seat: Seat, term: int, holder: str | None, now_ns: int, reason: str
    ) -> Change | None:
        """Another holder (or term): its lease starts now, whatever the last one left unanswered."""
        was_mine = seat.holder == self.me
        seat.term, seat.holder = term, holder
        seat.holder_since_ns = now_ns
        seat.answered_seq = -1
        seat.unanswered_since_ns = None
        if was_mine and holder != self.me:
            return self._step_down(uav, seat, now_ns, reason)
        return None

    def forget(self, uav: str) -> None:
        self.seats.pop(uav, None)
        self._orders.pop(uav, None)

    # decisions ---------------------------------------------------------------------------------------
    def _step_down(self, uav: str, seat: Seat, now_ns: int, reason: str) -> Change:
        seat.displaced_ns = now_ns
        self.counters.stepped_down += 1
        return Change(uav, self.role(uav), seat.term, f"stepped down: {reason}")

    def _maybe_take(self, uav: str, seat: Seat, now_ns: int) -> Change | None:
        if seat.holder == self.me:
            return None
        order = self.order(uav)
        holder = seat.holder
        if holder is None and not self.drone_arbitrates and len(self.members) > 1:
            # Nobody told us who holds it (the drone does not say): give the peers a lease to speak up,
            # so that a replica that (re)starts does not take a drone that another one serves.
            waited = seat.unanswered_since_ns
            if waited is None or now_ns - waited <= self.lease_ns:
                return None
            candidates, reason = order, f"no replica served it for {(now_ns - waited) / 1e6:.0f} ms"
        elif holder is None or holder not in self.members:
            candidates, reason = order, f"holder {holder or '(none)'} is gone"
        elif order.index(holder) > order.index(self.me) and not self._holding_off(seat, now_ns):
            candidates, reason = order, f"ranked above {holder}"
        elif (silent_ns := self._silent_ns(seat, holder, now_ns)) > self.lease_ns:
            # also when we rank above the holder but hold off: a holder that took the drone from us
            # and then hung is replaced by its standby, which is us (the candidates skip the holder)
            late_ms = silent_ns / 1e6
            candidates, reason = [r for r in order if r != holder], f"{holder} silent for {late_ms:.0f} ms"
        else:
            return None
        if not candidates or candidates[0] != self.me:
            return None
        seat.term += 1
        seat.holder = self.me
        seat.holder_since_ns = now_ns
        seat.unanswered_since_ns = None
        seat.displaced_ns = None
        self.counters.takeovers += 1
        return Change(uav, Role.SERVE, seat.term, f"took over: {reason}")

    def _holding_off(self, seat: Seat, now_ns: int) -> bool:
        """Displaced a moment ago: a drone is not taken back by rank alone (silence still takes it)."""
        return seat.displaced_ns is not None and now_ns - seat.displaced_ns < self.holdoff_ns

    def _silent_ns(self, seat: Seat, holder: str, now_ns: int) -> int:
        """How long the holder has been silent: with `beats`, from its last heartbeat (or from when it
        took the drone, if later) to our loop's time (`on_turn`); else since the oldest state it left
        unanswered (-1: none waits)."""
        if self.beats:
            return min(now_ns, self.loop_ns) - max(self.beat_ns.get(holder, 0), seat.holder_since_ns)
        return -1 if seat.unanswered_since_ns is None else now_ns - seat.unanswered_since_ns

    def tick(self, now_ns: int) -> list[Change]:
        """Takeovers due now without a new message: a holder's token went, or its lease ran out. With
        `beats`, the seats are looked at only after the live set changed or while a peer is silent (a
        seat's holder is silent no longer than the replica itself): not every drone every period."""
        if self.beats and not self._rescan and not self._a_peer_is_silent(now_ns):
            return []
        self._rescan = False
        changes = []
        for uav, seat in self.seats.items():
            if seat.holder != self.me and seat.latest_seq >= 0 and self.role(uav) is Role.WATCH:
                change = self._maybe_take(uav, seat, now_ns)
                if change is not None:
                    changes.append(change)
        return changes

    def late_peers(self, now_ns: int, after_ns: int) -> set[str]:
        """The other live replicas (with `beats`) heard, and not for `after_ns` since, on our loop's time
        (`on_turn`): a standby listens to each state of their drones before their lease runs out. One not
        heard yet is not late: it has not turned, so flies no drone (its takeovers come from its loop)."""
        heard = min(now_ns, self.loop_ns)
        return {r for r, beat_ns in self.beat_ns.items() if r in self.members and heard - beat_ns > after_ns}

    def _a_peer_is_silent(self, now_ns: int) -> bool:
        heard = min(now_ns, self.loop_ns)
        return any(heard - self.beat_ns.get(r, 0) > self.lease_ns for r in self.members if r != self.me)

    def term(self, uav: str) -> int:
        seat = self.seats.get(uav)
        return 0 if seat is None else seat.term

    def holder(self, uav: str) -> str | None:
        """The replica the drone follows, as this one knows it (None: not known)."""
        seat = self.seats.get(uav)
        return None if seat is None else seat.holder
