"""Which MPC replica flies which drone (edge/replicas.py), and the drone's fencing (onboard/commands.py).

Pure, on nanosecond timestamps: the assignment is a function of the live set, the states and the
commands seen, so every takeover rule is checked without processes."""

from __future__ import annotations

import itertools

import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority, Publisher, Received
from dynqos.common.clock import FakeClock
from dynqos.common.config import load_config
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command, Reference, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.reference import ReferenceTrack
from dynqos.edge.mpc.service import MpcService
from dynqos.edge.planner.service import PlannerService
from dynqos.edge.replicas import MAX_REPLICAS, Assignment, Role, ranked
from dynqos.edge.runtime import Ports
from dynqos.onboard.commands import CommandTracker
from tests.edge_cores import take, turn

MS = 1_000_000
LEASE = 50 * MS
HOLDOFF = 2000 * MS


def replica(me: str, *others: str) -> Assignment:
    a = Assignment(me, lease_ns=LEASE, holdoff_ns=HOLDOFF)
    for other in others:
        a.join(other)
    return a


def drone_ranked(first: str, second: str, members: tuple[str, ...] = ("a", "b", "c")) -> str:
    """A drone id whose rendezvous order over `members` starts with first, second."""
    for i in range(10_000):
        uav = f"uav{i}"
        if ranked(uav, members)[:2] == [first, second]:
            return uav
    raise AssertionError("no such drone")


def test_rendezvous_moves_only_the_drones_of_the_replica_that_joins_or_leaves() -> None:
    drones = [f"uav{i}" for i in range(300)]
    before = {u: ranked(u, ["a", "b", "c"])[0] for u in drones}
    after_leave = {u: ranked(u, ["a", "c"])[0] for u in drones}
    moved = {u for u in drones if before[u] != after_leave[u]}
    assert moved == {u for u in drones if before[u] == "b"}  # only b's drones move
    assert 60 < len(moved) < 140  # and b had about a third of them
    after_join = {u: ranked(u, ["a", "b", "c", "d"])[0] for u in drones}
    assert {u for u in drones if before[u] != after_join[u]} == {u for u in drones if after_join[u] == "d"}


def test_a_lone_replica_takes_every_drone_with_the_next_term() -> None:
    a = replica("a")
    change = a.on_state("uav1", 1, drone_term=4, drone_holder="old", now_ns=0)
    assert change is not None
    assert change.role is Role.SERVE
    assert change.term == 5
    assert a.role("uav1") is Role.SERVE


def test_the_standby_waits_while_the_primary_answers_and_takes_over_when_it_falls_silent() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    primary, standby = replica("a", "b"), replica("b", "a")
    assert primary.on_state(uav, 1, 0, "", 0) is not None  # a takes the drone: term 1
    assert standby.on_state(uav, 1, 0, "", 0) is None
    t = 0
    for seq in range(1, 20):  # a answers every state within 10 ms
        t = seq * 50 * MS
        standby.on_state(uav, seq, 1, "a", t)
        standby.on_command(uav, seq, 1, "a", t + 10 * MS)
        assert standby.tick(t + 45 * MS) == []
    assert standby.role(uav) is Role.WATCH
    standby.on_state(uav, 20, 1, "a", t + 50 * MS)  # a hangs: state 20 is never answered
    assert standby.tick(t + 50 * MS + LEASE) == []  # not before the lease
    changes = standby.tick(t + 51 * MS + LEASE)
    assert [(c.uav, c.role, c.term) for c in changes] == [(uav, Role.SERVE, 2)]
    assert "silent" in changes[0].reason


def test_a_replica_whose_token_goes_is_replaced_at_once_without_waiting_for_the_lease() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    standby = replica("b", "a")
    standby.on_state(uav, 1, 3, "a", 0)
    standby.on_command(uav, 1, 3, "a", 1 * MS)
    assert standby.tick(2 * MS) == []
    standby.leave("a")
    changes = standby.tick(3 * MS)
    assert [(c.role, c.term) for c in changes] == [(Role.SERVE, 4)]


def test_a_hung_replica_that_comes_back_steps_down_on_the_newer_term() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    hung = replica("a", "b")
    assert hung.on_state(uav, 1, 0, "", 0) is not None
    assert hung.role(uav) is Role.SERVE
    # while it was stopped, b took over with term 2; the drone now follows b
    change = hung.on_command(uav, 30, 2, "b", 2000 * MS)
    assert change is not None
    assert change.role is Role.WATCH
    assert "b holds term 2" in change.reason
    assert hung.role(uav) is Role.WATCH
    # it is ranked first, yet it waits the hold-off before taking the drone back
    hung.on_state(uav, 31, 2, "b", 2001 * MS)
    hung.on_command(uav, 31, 2, "b", 2002 * MS)
    assert hung.tick(2100 * MS) == []
    hung.on_state(uav, 80, 2, "b", 4100 * MS)
    assert hung.role(uav) is Role.SERVE
    assert hung.term(uav) == 3


def test_a_joining_replica_ranked_first_takes_the_drone_and_the_old_holder_steps_down() -> None:
    uav = drone_ranked("c", "a", ("a", "b", "c"))
    old = replica("a", "b")  # before c joins, a is first for this drone
    assert old.on_state(uav, 1, 0, "", 0) is not None
    new = replica("c", "a", "b")
    change = new.on_state(uav, 2, 1, "a", 10 * MS)
    assert change is not None
    assert change.term == 2
    assert "ranked above a" in change.reason
    old.join("c")
    stepped = old.on_command(uav, 2, 2, "c", 12 * MS)
    assert stepped is not None
    assert old.role(uav) is Role.WATCH


def test_two_replicas_with_the_same_term_follow_the_drone() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    b = replica("b")  # b did not know of a and took the drone with term 1
    assert b.on_state(uav, 1, 0, "", 0) is not None
    b.join("a")
    change = b.on_state(uav, 2, 1, "a", 50 * MS)  # the drone accepted a's term 1
    assert change is not None
    assert b.role(uav) is Role.WATCH


def test_a_replica_neither_primary_nor_standby_is_idle_and_stale_commands_are_counted() -> None:
    uav = drone_ranked("a", "b")
    c = replica("c", "a", "b")
    assert c.role(uav) is Role.IDLE
    assert not c.mine(uav)
    c.on_command(uav, 5, 3, "a", 0)
    c.on_command(uav, 6, 2, "x", 1)
    assert c.counters.stale_commands == 1


def test_a_token_flood_and_bad_names_are_refused() -> None:
    a = replica("a")
    assert not a.join("bad/name")
    for i in range(MAX_REPLICAS + 10):
        a.join(f"r{i}")
    assert len(a.members) == MAX_REPLICAS
    assert a.counters.members_refused == 1 + 11  # the bad name, then the flood
    with pytest.raises(ValueError, match="replica id"):
        Assignment("", lease_ns=1, holdoff_ns=1)


def _command(state_seq: int, stamp: int, term: int, replica_id: str) -> Command:
    return Command(uav="uav1", seq=state_seq, state_seq=state_seq, state_stamp_ns=stamp, edge_hold_ns=0,
                   dt_s=0.05, accel_mps2=((0.0, 0.0, 0.0),) * 10, yaw_rad=(0.0,) * 10, term=term,
                   replica=replica_id)  # fmt: skip


def test_the_drone_follows_the_highest_term_and_refuses_a_replaced_or_second_controller() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    for seq in range(1, 6):
        tracker.state_sent(seq, seq * 50 * MS)
    assert tracker.offer(_command(1, 50 * MS, 1, "a"), 60 * MS)
    assert (tracker.term, tracker.replica) == (1, "a")
    assert not tracker.offer(_command(2, 100 * MS, 1, "b"), 110 * MS)  # same term, another replica
    assert tracker.offer(_command(2, 100 * MS, 2, "b"), 111 * MS)  # b took over
    assert tracker.counters.controller_changes == 1
    assert not tracker.offer(_command(3, 150 * MS, 1, "a"), 160 * MS)  # a came back with its old term
    assert tracker.counters.fenced == 2
    assert tracker.offer(_command(3, 150 * MS, 2, "b"), 161 * MS)
    assert tracker.longest_gap_ns == 51 * MS  # 60 -> 111 ms


def test_a_drone_known_only_from_commands_is_not_taken_until_its_state_arrives() -> None:
    uav = drone_ranked("b", "a", ("a", "b"))
    b = replica("b")
    b.on_command(uav, 7, 3, "a", 0)  # a, in another group, flies it: b has no state to answer
    assert b.tick(10 * MS) == []
    assert b.on_state(uav, 8, 3, "a", 20 * MS) is not None  # a is not in b's live set: b takes it


def _mpc(name: str, bus: MemoryBus, clock: FakeClock, reads: str = "states") -> MpcService:
    config = load_config(None, [f'mpc.replica_id="{name}"', f'mpc.standby_reads="{reads}"'])
    return MpcService(config, Ports(bus, clock))


def _drone_and_commands(bus: MemoryBus) -> tuple[Publisher, BoundedQueue[Received]]:
    """uav1's State publisher, and every Command sent to it."""
    commands: BoundedQueue[Received] = BoundedQueue(1000)
    bus.subscribe(keys.downlink("uav1", Downlink.COMMAND), commands, expect=(Command,))
    return bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME), commands


def _state(seq: int, clock: FakeClock, term: int, holder: str) -> State:
    return State(uav="uav1", seq=seq, stamp_ns=clock.now_ns(), pos_m=(0.0, 0.0, -1.5),
                 vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), command_term=term,
                 command_replica=holder)  # fmt: skip


def beating(me: str, *others: str) -> Assignment:
    a = Assignment(me, lease_ns=LEASE, holdoff_ns=HOLDOFF, beats=True)
    for other in others:
        a.join(other)
    return a


TURN = 10 * MS  # the MPC's loop turns once per beat period


def turns(a: Assignment, start_ns: int, count: int, beats_from: str | None = None) -> int:
    """`count` turns of our loop on time after `start_ns` (a peer beating at each, if named); the last."""
    t = start_ns
    for _ in range(count):
        t += TURN
        a.on_turn(t, TURN)
        if beats_from:
            a.on_beat(beats_from, t)
    return t


def test_with_beats_a_standby_takes_over_when_the_holders_beats_stop_not_when_a_state_waits() -> None:
    """The MPC's leases: the holder is silent when its heartbeat stops; a standby needs no commands."""
    uav = drone_ranked("a", "b", ("a", "b"))
    standby = beating("b", "a")
    standby.on_turn(0, TURN)
    standby.on_state(uav, 1, 1, "a", 0)  # the drone follows a
    t = 0
    for seq in range(2, 30):  # a beats every 10 ms; no command is ever seen, and none is needed
        t = turns(standby, t, 5, beats_from="a")
        assert standby.on_state(uav, seq, 1, "a", t) is None
        assert standby.tick(t) == []
    assert standby.role(uav) is Role.WATCH
    last_beat = t  # a hangs: its beats stop, the drone's states go on, our loop turns on
    t = turns(standby, t, 5)
    assert standby.on_state(uav, 30, 1, "a", t) is None  # not before the lease
    assert standby.tick(t) == []
    standby.on_turn(last_beat + LEASE + MS, TURN)
    change = standby.on_state(uav, 31, 1, "a", last_beat + LEASE + MS)
    assert change is not None
    assert (change.role, change.term) == (Role.SERVE, 2)
    assert "silent" in change.reason
    assert standby.counters.own_stalls == 0
    standby.on_beat("b", t)  # its own beats and a stranger's are not a peer's
    standby.on_beat("zed", t)
    assert set(standby.beat_ns) == {"a"}


def test_with_beats_a_standby_that_stalled_does_not_take_its_own_stall_for_its_peers_silence() -> None:
    """A replica descheduled (or its loop holding the GIL) received nothing meanwhile; on its first turn
    after, its peer's backlog of beats still waits on zenoh's threads. Its time is held until it came."""
    uav = drone_ranked("a", "b", ("a", "b"))
    standby = beating("b", "a")
    standby.on_turn(0, TURN)
    standby.on_state(uav, 1, 1, "a", 0)
    t = turns(standby, 0, 3, beats_from="a")
    assert standby.on_turn(t + 2 * TURN - MS, TURN) == 0  # late by under a beat period: jitter, no stall
    assert standby.counters.own_stalls == 0
    stall_ends = t + 2 * TURN - MS + 10 * LEASE  # a stall of our own: nothing heard, no turn
    assert standby.on_turn(stall_ends, TURN) == 10 * LEASE
    assert standby.counters.own_stalls == 1
    t = stall_ends
    assert standby.tick(t) == []
    assert standby.on_state(uav, 2, 1, "a", t) is None
    t = turns(standby, t, 5, beats_from="a")  # the backlog comes in: a beats, nothing is taken
    assert standby.tick(t) == []
    assert standby.role(uav) is Role.WATCH


def test_with_beats_a_peer_silent_across_our_own_stall_is_taken_over_once_the_hold_ends() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    standby = beating("b", "a")
    standby.on_turn(0, TURN)
    standby.on_state(uav, 1, 1, "a", 0)
    t = turns(standby, 0, 3, beats_from="a")
    t += 10 * LEASE  # we stall; a hangs meanwhile, and no backlog comes
    standby.on_turn(t, TURN)
    assert standby.tick(t) == []
    t = turns(standby, t, 1)
    assert standby.tick(t) == []  # still held (twice the stall threshold)
    t = turns(standby, t, 1)
    changes = standby.tick(t)  # no state since: our own loop's time alone tells
    assert [(c.role, c.term) for c in changes] == [(Role.SERVE, 2)]


def test_with_beats_a_new_holder_gets_a_whole_lease_before_its_first_beat() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    standby = beating("b", "a")
    t = turns(standby, 1000 * MS - TURN, 1)
    standby.on_state(uav, 1, 1, "a", t)  # a is known to hold it from now; no beat heard yet
    t = turns(standby, t, 5)
    standby.on_state(uav, 2, 1, "a", t)
    assert standby.tick(t) == []
    standby.on_turn(t + MS, TURN)
    change = standby.on_state(uav, 3, 1, "a", t + MS)
    assert change is not None
    assert change.role is Role.SERVE


def test_a_replica_holding_off_still_replaces_the_holder_that_displaced_it_and_then_hung() -> None:
    """b is the drone's primary; its standby a took the drone while b's loop was late (a loaded host),
    and b stepped down, holding off its rank for two seconds. a then hangs: b, the only other replica,
    takes the drone when a's beats stop, within a lease, not once its holdoff ends (a CI flight's drones
    fell back at the watchdog waiting for that)."""
    uav = drone_ranked("b", "a", ("a", "b"))
    b = beating("b", "a")
    t = turns(b, 0, 1, beats_from="a")
    assert b.on_state(uav, 1, 0, "", t) is not None  # nobody flies it yet: b, ranked first, takes it
    t = turns(b, t, 5, beats_from="a")
    step_down = b.on_state(uav, 2, 2, "a", t)  # a took it while b was late
    assert step_down is not None
    assert step_down.role is Role.WATCH
    t = turns(b, t, 5, beats_from="a")
    assert b.on_state(uav, 3, 2, "a", t) is None  # a beats: holding off, b does not take back by rank
    assert b.tick(t) == []
    last_beat = t  # a hangs
    t = turns(b, t, 4)
    assert b.tick(t) == []  # within the lease
    t = turns(b, t, 2)
    changes = b.tick(t)
    assert [(c.role, c.term) for c in changes] == [(Role.SERVE, 3)], changes
    assert "a silent for" in changes[0].reason
    assert t - last_beat < HOLDOFF / 10


def test_without_beats_a_replica_holding_off_replaces_a_silent_holder_within_the_lease() -> None:
    uav = drone_ranked("b", "a", ("a", "b"))
    b = replica("b", "a")
    assert b.on_state(uav, 1, 0, "", 0) is not None
    assert b.on_command(uav, 1, 2, "a", 10 * MS) is not None  # a took it: b steps down
    assert b.on_state(uav, 2, 2, "a", 50 * MS) is None
    assert b.on_command(uav, 2, 2, "a", 55 * MS) is None
    assert b.on_state(uav, 3, 2, "a", 100 * MS) is None  # a answers no more
    assert b.tick(100 * MS + LEASE) == []
    changes = b.tick(100 * MS + LEASE + MS)
    assert [(c.role, c.term) for c in changes] == [(Role.SERVE, 3)], changes


def test_the_rank_cache_follows_the_live_set() -> None:
    a = replica("a", "b")
    uav = drone_ranked("c", "a", ("a", "b", "c"))
    assert a.order(uav) == ranked(uav, {"a", "b"})
    a.join("c")
    assert a.order(uav)[:2] == ["c", "a"]
    a.leave("c")
    assert a.order(uav) == ranked(uav, {"a", "b"})


@pytest.mark.parametrize("reads", ["states", "copies"])
def test_a_hung_mpc_service_is_replaced_when_its_beats_stop_and_no_standby_hears_commands(reads: str) -> None:
    """Two MPC services on the in-memory bus: the standby subscribes to no commands; when the one flying
    the drone stops turning (hung: no beats, no answers), the standby answers within the lease."""
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))
    a, b = _mpc("mpc-a", bus, clock, reads), _mpc("mpc-b", bus, clock, reads)
    drone, commands = _drone_and_commands(bus)
    followed = (0, "")
    got: list[Command] = []
    live = [a, b]
    for seq in range(1, 40):
        drone.put(_state(seq, clock, *followed))
        for _ in range(5):  # 10 ms turns: each live service beats and answers
            for service in live:
                turn(service, clock.now_ns())
            got += [i.message for i in commands.drain() if isinstance(i.message, Command)]
            clock.advance_s(0.01)
        if got:
            followed = (got[-1].term, got[-1].replica)
        if seq == 10:
            flying = a if got[-1].replica == "mpc-a" else b
            live.remove(flying)  # hung: its token stays, it neither beats nor answers
            hung_at = len(got)
    standby = live[0]
    assert len([c for c in got[:hung_at] if c.replica == standby.replica]) == 0  # it stood by, silent
    after = got[hung_at:]
    assert after
    assert {(c.replica, c.term) for c in after} == {(standby.replica, got[hung_at - 1].term + 1)}
    assert after[0].state_seq == 12  # state 11 came as it hung; 12 as the lease (50 ms) ran out
    assert standby.feeds.subscribed == {"uav1"}
    inputs = {feed.all_drones for feed in standby.feeds.feeds}  # the commands are the drone's alone
    assert keys.downlink_all_drones(Downlink.COMMAND) not in inputs


def _pair(clock: FakeClock, reads: str = "states") -> tuple[MemoryBus, MpcService, MpcService]:
    """Two MPC services on one in-memory bus, uav1 present; the one ranked first for it, then the other."""
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))
    a, b = _mpc("mpc-a", bus, clock, reads), _mpc("mpc-b", bus, clock, reads)
    for service in (a, b):
        turn(service, clock.now_ns())
    first = a if ranked("uav1", {"mpc-a", "mpc-b"})[0] == "mpc-a" else b
    return bus, first, b if first is a else a


def test_a_standby_reads_the_holders_few_copies_and_takes_each_state_once_it_flies() -> None:
    """A drone a replica stands by for: it reads the holder's copies of the drone's states (two a
    second, and each that says the drone follows another term), not each state; once it takes the
    drone over, it answers the drone's own next state, not a copy, and the states come to it one by one."""
    clock = FakeClock(1_000_000_000)
    bus, first, second = _pair(clock, "copies")
    assert set(second.feeds.pulled) == {"uav1"}
    assert not first.feeds.pulled
    drone = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
    followed = (0, "")
    for seq in range(1, 21):  # one second at 20 Hz
        drone.put(_state(seq, clock, *followed))
        for _ in range(5):
            for service in (first, second):
                turn(service, clock.now_ns())
            clock.advance_s(0.01)
        followed = (first.assignment.term("uav1"), first.replica)
    assert first.counters.states == 20  # the one that flies it hears each
    # and copies one at once when the drone follows it (seq 2: term 1), then one every 500 ms
    assert first.counters.watch_copies == 3
    assert second.counters.states <= 3  # the standby reads those copies only (newest-only: maybe fewer)
    assert second.assignment.term("uav1") == first.assignment.term("uav1") == 1
    assert [second.newest["uav1"].message.seq, second.newest["uav1"].key] == [
        12,
        keys.state_watch("mpc", "all", "uav1"),
    ]
    assert second.assignment.seats["uav1"].holder == first.replica
    assert not second.counters.alerts  # the holder beat all along
    first.membership.token.close()  # its process is gone
    turn(second, clock.now_ns())
    assert second.assignment.role("uav1") is Role.SERVE
    assert second.counters.commands == 0  # a copy is not the drone's newest state: nothing answered yet
    assert not second.feeds.pulled  # flying it now: pushed each state
    drone.put(_state(21, clock, *followed))
    turn(second, clock.now_ns())
    assert second.counters.commands == 1
    assert second.assignment.term("uav1") == followed[0] + 1


def test_a_standby_takes_each_state_once_the_holders_beats_are_late_and_reads_copies_again_after() -> None:
    """Beats three periods late: the standby takes the drone's states in full before the lease runs out,
    so that it answers the first state after it; a holder that beats again is read from its copies
    once the alert has held for 300 ms."""
    clock = FakeClock(1_000_000_000)
    bus, first, second = _pair(clock, "copies")
    drone = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
    for seq in range(1, 11):
        drone.put(_state(seq, clock, first.assignment.term("uav1"), first.replica))
        for _ in range(5):
            for service in (first, second):
                turn(service, clock.now_ns())
            clock.advance_s(0.01)
    assert set(second.feeds.pulled) == {"uav1"}
    for _ in range(4):  # the holder stalls for 40 ms (not hung: it comes back inside its lease)
        turn(second, clock.now_ns())
        clock.advance_s(0.01)
    turn(second, clock.now_ns())
    assert second.counters.alerts == 1
    assert not second.feeds.pulled  # each state now
    read = second.counters.states
    drone.put(_state(11, clock, first.assignment.term("uav1"), first.replica))
    for _ in range(5):
        for service in (first, second):
            turn(service, clock.now_ns())
        clock.advance_s(0.01)
    assert second.counters.states == read + 1
    assert not keys.is_state_watch(second.newest["uav1"].key)  # the drone's own state, not a copy
    assert second.assignment.role("uav1") is Role.WATCH  # the holder came back in its lease
    assert not second.feeds.pulled  # the alert holds for 300 ms
    for _ in range(40):
        for service in (first, second):
            turn(service, clock.now_ns())
        clock.advance_s(0.01)
    assert set(second.feeds.pulled) == {"uav1"}  # quiet again
    assert second.counters.alerts == 1


def test_a_standby_reads_the_drones_states_twice_a_second_and_each_beat_once_the_holder_is_late() -> None:
    """`standby_reads = "states"`: the drone's own states wait newest-only in zenoh and are read twice a
    second (no copies); once the holder's beats are three periods late they are read each beat period,
    with no new subscription to wait for, so the takeover answers the drone's newest state at once."""
    clock = FakeClock(1_000_000_000)
    bus, first, second = _pair(clock)
    drone, commands = _drone_and_commands(bus)

    followed = (0, "")

    def fly(seqs: range, services: list[MpcService]) -> list[Command]:
        nonlocal followed
        got: list[Command] = []
        for seq in seqs:
            drone.put(_state(seq, clock, *followed))
            for _ in range(5):
                for service in services:
                    turn(service, clock.now_ns())
                clock.advance_s(0.01)
            got += [i.message for i in commands.drain() if isinstance(i.message, Command)]
            followed = (got[-1].term, got[-1].replica) if got else followed
        return got

    assert {c.replica for c in fly(range(1, 21), [first, second])} == {first.replica}
    assert first.counters.states == 20
    assert first.counters.watch_copies == 0  # nobody reads copies
    assert second.counters.states <= 4  # twice a second, and once as the drone came
    assert not keys.is_state_watch(second.newest["uav1"].key)
    assert second.assignment.seats["uav1"].holder == first.replica
    read = second.counters.states
    assert fly(range(21, 22), [second]) == []  # the holder hangs: state 21 is answered by no one
    assert second.counters.alerts == 1
    assert second.assignment.role("uav1") is Role.WATCH
    assert set(second.feeds.pulled) == {"uav1"}  # still read from zenoh's slot: no new subscription
    assert second.newest["uav1"].message.seq == 21  # read at the alert, not half a second later
    after = fly(range(22, 26), [second])
    assert second.counters.states >= read + 2
    assert after[0].state_seq == 22  # the lease (50 ms after its last beat): the state that came then
    assert {(c.replica, c.term) for c in after} == {(second.replica, 2)}
    assert [c.state_seq for c in after] == list(range(22, 26))


@pytest.mark.parametrize(("reads", "first_answered"), [("copies", 12), ("states", 11)])
def test_two_mpc_services_on_one_bus_hand_the_drone_over_when_the_flying_one_goes(
    reads: str, first_answered: int
) -> None:
    """The service wiring on the in-memory bus (same codec and checks as zenoh) and a fake clock: the
    drone's states, the commands each replica sees of the other, the tokens; a token flood is counted.
    A standby that read the holder's copies answers the drone's next state after the holder's token
    went; one that read each state answers the newest at once."""
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))  # the drone's daemon announces it
    a, b = _mpc("mpc-a", bus, clock, reads), _mpc("mpc-b", bus, clock, reads)
    drone, commands = _drone_and_commands(bus)
    followed = (0, "")

    def step(seq: int, services: list[MpcService]) -> list[Command]:
        nonlocal followed
        drone.put(_state(seq, clock, *followed))
        for service in services:
            turn(service, clock.now_ns())
        got = [i.message for i in commands.drain() if isinstance(i.message, Command)]
        for service in services:  # each sees the commands sent in this round (the other's too)
            turn(service, clock.now_ns())
        if got:
            followed = (got[-1].term, got[-1].replica)
        clock.advance_s(0.05)
        return got

    first = [c for seq in range(1, 11) for c in step(seq, [a, b])]
    assert len(first) == 10  # one answer per state: the standby stays silent
    flying = first[-1].replica
    assert {c.replica for c in first} == {flying}
    survivor = b if flying == "mpc-a" else a
    (
        a if flying == "mpc-a" else b
    ).membership.token.close()  # its process is gone: the router withdraws the token
    after = [c for seq in range(11, 16) for c in step(seq, [survivor])]
    # with copies, state 11 came while the survivor read the holder's copies only
    assert [c.state_seq for c in after] == list(range(first_answered, 16))
    assert {(c.replica, c.term) for c in after} == {(survivor.replica, first[-1].term + 1)}
    for i in range(300):  # a flood of replica tokens: the live set stops growing, each is counted
        bus.declare_token(keys.replica_token("mpc", "all", f"x{i}"))
    turn(survivor, clock.now_ns())
    assert len(survivor.assignment.members) == 256
    assert survivor.assignment.counters.members_refused == 300 - 255


def test_a_replica_that_never_hears_its_own_commands_does_not_take_back_at_once_when_displaced() -> None:
    """A replica subscribes to other replicas' commands only, so while it flies a drone it hears no
    answer to the states it sees; displaced, it must time the new holder from then, not from then."""
    uav = drone_ranked("c", "b", ("b", "c"))
    b = replica("b")
    t = 0
    for seq in range(1, 60):  # b flies alone for 3 s, hearing none of its own commands
        t = seq * 50 * MS
        b.on_state(uav, seq, 1, "b", t)
    b.join("c")
    change = b.on_command(uav, 59, 2, "c", t + 5 * MS)  # c joined ranked first and took the drone
    assert change is not None
    assert change.role is Role.WATCH
    assert b.tick(t + 6 * MS) == []  # no "c silent for 3000 ms"
    b.on_state(uav, 60, 2, "c", t + 50 * MS)
    assert b.tick(t + 50 * MS + LEASE + MS) != []  # c really silent now: b takes over after the lease


def test_a_standby_planner_continues_the_mission_where_the_one_it_replaces_left_it() -> None:
    """Two planners on the in-memory bus: one publishes, the other follows its mission time from the
    references; when the first one's token goes, the second publishes the same mission, continued."""
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))
    planners = [
        PlannerService(load_config(None, [f'planner.replica_id="{n}"']), Ports(bus, clock)) for n in "pq"
    ]
    refs: BoundedQueue[Received] = BoundedQueue(1000)
    bus.subscribe(keys.downlink("uav1", Downlink.REFERENCE), refs, expect=(Reference,))
    drone = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)

    def run(seconds: float, live: list[PlannerService]) -> list[Reference]:
        for k in range(round(seconds / 0.05)):
            drone.put(_state(k + 1, clock, 0, ""))
            for planner in live:
                take(planner, clock.now_ns())
                planner.discover(clock.now_ns())
                if k % 2 == 0:
                    planner.publish()
            clock.advance_s(0.05)
        return [i.message for i in refs.drain() if isinstance(i.message, Reference)]

    before = run(3.0, planners)
    assert len({r.replica for r in before}) == 1  # one publishes, the other stands by
    first = next(p for p in planners if p.replica == before[-1].replica)
    second = next(p for p in planners if p is not first)
    first.membership.token.close()  # its process is gone
    after = run(1.0, [second])
    assert {r.replica for r in after} == {second.replica}
    assert after[0].term > before[-1].term
    # the mission goes on: its time continues from where it was, it does not start again at 0
    assert after[0].mission_t_s == pytest.approx(before[-1].mission_t_s + 0.1, abs=0.06)

    # The first one restarts (same id, a new process): it learns the holder from its references before
    # it takes the drone back (it ranks first), and goes on from the same mission time.
    restarted = PlannerService(
        load_config(None, [f'planner.replica_id="{first.replica}"']), Ports(bus, clock)
    )
    back = run(1.0, [second, restarted])
    assert back[-1].replica == first.replica
    assert back[-1].term > after[-1].term
    times = [r.mission_t_s for r in before + after + back]
    assert all(b >= a for a, b in itertools.pairwise(times)), "a planner restarted the mission"
    # and a receiver (the MPC, the drone's fallback) takes every one of them as the newest
    track = ReferenceTrack()
    assert all(track.update(r, 0) for r in before + after + back)


def _ref(term: int, replica_id: str, seq: int) -> Reference:
    return Reference(uav="uav1", seq=seq, stamp_ns=0, dt_s=0.1, pos_m=((0.0, 0.0, -1.0),),
                     vel_mps=((0.0, 0.0, 0.0),), yaw_rad=(0.0,), term=term, replica=replica_id)  # fmt: skip


def test_a_receiver_takes_the_newest_planner_term_whatever_the_replicas_seq() -> None:
    track = ReferenceTrack()
    assert track.update(_ref(1, "p", 500), 0)
    assert not track.update(_ref(1, "p", 499), 0)  # older, from the same replica
    assert track.update(_ref(2, "q", 3), 0)  # a replica that took over counts from its own seq
    assert not track.update(_ref(1, "p", 501), 0)  # the replaced one, back after a hang: ignored
    assert track.update(_ref(2, "p", 502), 0)  # two on one term for a moment: the latest arrival
    assert track.reference is not None
    assert track.reference.replica == "p"


def test_a_planner_that_starts_beside_a_peer_waits_a_lease_before_it_takes_an_unheard_drone() -> None:
    uav = drone_ranked("a", "b", ("a", "b"))
    a = Assignment("a", lease_ns=LEASE, holdoff_ns=HOLDOFF, drone_arbitrates=False)
    a.join("b")
    assert a.on_state(uav, 1, 0, "", 0) is None  # b may hold it: a has heard no reference yet
    assert a.tick(LEASE) == []
    change = a.on_command(uav, 1, 4, "b", LEASE)  # b's reference: b holds term 4
    assert change is None
    assert a.seats[uav].holder == "b"
    taken = a.on_state(uav, 2, 0, "", LEASE + MS)  # a ranks first: it takes over from b, term 5
    assert taken is not None
    assert taken.term == 5
    c = Assignment("a", lease_ns=LEASE, holdoff_ns=HOLDOFF, drone_arbitrates=False)
    c.join("b")
    c.on_state(uav, 1, 0, "", 0)
    late = c.tick(LEASE + MS)  # nobody spoke for a lease: a takes it
    assert [x.term for x in late] == [1]
    assert "no replica served it" in late[0].reason
