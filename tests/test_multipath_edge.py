"""Two edge sites answer every drone (docs/multipath.md): replicas share a drone and fence one another
within their site, never across; the service wiring on the in-memory bus (the same codec and checks as
zenoh, one bus as linked routers make) and a fake clock."""

from __future__ import annotations

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority, Received
from dynqos.common.clock import FakeClock
from dynqos.common.config import load_config
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command, State
from dynqos.common.queues import BoundedQueue
from dynqos.edge.mpc.service import MpcService, followed_at
from dynqos.edge.runtime import Ports
from dynqos.onboard.commands import CommandTracker
from tests.edge_cores import turn

MS = 1_000_000


def _mpc(name: str, site: str, bus: MemoryBus, clock: FakeClock) -> MpcService:
    return MpcService(
        load_config(None, [f'mpc.replica_id="{name}"', f'mpc.site="{site}"']), Ports(bus, clock)
    )


def test_each_site_answers_every_state_and_a_site_keeps_its_own_terms() -> None:
    clock = FakeClock(1_000 * MS)
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))
    site_a = [_mpc("a1", "a", bus, clock), _mpc("a2", "a", bus, clock)]
    site_b = [_mpc("b1", "b", bus, clock)]
    commands: BoundedQueue[Received] = BoundedQueue(1000)
    bus.subscribe(keys.downlink("uav1", Downlink.COMMAND), commands, expect=(Command,))
    drone = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)

    def step(seq: int, services: list[MpcService]) -> list[Command]:
        state = State(uav="uav1", seq=seq, stamp_ns=clock.now_ns(), pos_m=(0.0, 0.0, -1.5),
                      vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), command_term=tracker.term,
                      command_replica=tracker.replica, controllers=tracker.controllers())  # fmt: skip
        tracker.state_sent(seq, state.stamp_ns)
        drone.put(state)
        for service in services:
            turn(service, clock.now_ns())
        got = [i.message for i in commands.drain() if isinstance(i.message, Command)]
        for command in got:
            tracker.offer(command, clock.now_ns() + 5 * MS)
        for service in services:  # each sees the commands of this round (the other site's too)
            turn(service, clock.now_ns())
        clock.advance_s(0.05)
        return got

    first = [c for seq in range(1, 11) for c in step(seq, [*site_a, *site_b])]
    assert len(first) == 20  # one answer per state from each site: the standby at site a stays silent
    by_site = {site: {(c.replica, c.term) for c in first if c.site == site} for site in ("a", "b")}
    assert len(by_site["a"]) == 1
    assert by_site["b"] == {("b1", 1)}
    assert tracker.counters.duplicates == 10
    assert tracker.counters.fenced == 0
    ((flying, term),) = by_site["a"]
    # site a's holder goes: its standby takes the drone with site a's next term; site b flies on
    holder = next(s for s in site_a if s.replica == flying)
    standby = next(s for s in site_a if s is not holder)
    holder.membership.token.close()
    after = [c for seq in range(11, 16) for c in step(seq, [standby, *site_b])]
    assert {(c.site, c.replica, c.term) for c in after} == {("a", standby.replica, term + 1), ("b", "b1", 1)}
    assert tracker.counters.fenced == 0  # b's term 1 below a's: never compared
    assert dict((s, (t, r)) for s, t, r in tracker.controllers())["a"] == (term + 1, standby.replica)


def test_a_site_reads_its_own_entry_of_the_state() -> None:
    state = State(uav="uav1", seq=1, stamp_ns=1, pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                  quat=(1.0, 0.0, 0.0, 0.0), command_term=9, command_replica="x",
                  controllers=(("a", 3, "a1"), ("b", 1, "b1")))  # fmt: skip
    assert followed_at(state, "a") == (3, "a1")
    assert followed_at(state, "b") == (1, "b1")
    assert followed_at(state, "c") == (0, "")  # never answered first: nobody followed there yet
    assert followed_at(state, "") == (9, "x")  # one site: the State's own fields, as before


def _state(seq: int, stamp_ns: int, path: str) -> State:
    return State(uav="uav1", seq=seq, stamp_ns=stamp_ns, pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                 quat=(1.0, 0.0, 0.0, 0.0), path=path)  # fmt: skip


def test_a_site_answers_each_path_s_copy_of_a_state_with_the_same_command_under_its_path() -> None:
    """The drone times each path's uplink by the answers to that path's copy (onboard/paths.py): the
    first copy is solved, a later copy by another path gets the same Command again, at once if it was
    answered already, else once it is; a copy by a path already answered is stale."""
    clock = FakeClock(1_000 * MS)
    bus = MemoryBus(clock)
    bus.declare_token(keys.drone_presence("uav1"))
    mpc = _mpc("a1", "a", bus, clock)
    commands: BoundedQueue[Received] = BoundedQueue(1000)
    bus.subscribe(keys.downlink("uav1", Downlink.COMMAND), commands, expect=(Command,))
    drone = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
    turn(mpc, clock.now_ns())
    # both copies in one batch: the second waits for the solve of the first
    stamp = clock.now_ns()
    drone.put(_state(1, stamp, "a"))
    drone.put(_state(1, stamp, "b"))
    turn(mpc, clock.now_ns())
    first = [i.message for i in commands.drain()]
    assert [c.state_path for c in first] == ["a", "b"]
    assert first[0].accel_mps2 == first[1].accel_mps2
    assert {c.seq for c in first} == {1}
    # the next State's copy by path b arrives 30 ms after path a's, which is answered already
    clock.advance_s(0.05)
    stamp = clock.now_ns()
    drone.put(_state(2, stamp, "a"))
    turn(mpc, clock.now_ns())
    clock.advance_s(0.03)
    drone.put(_state(2, stamp, "b"))
    drone.put(_state(2, stamp, "b"))  # the same path's copy again: stale, not answered twice
    turn(mpc, clock.now_ns())
    second = [i.message for i in commands.drain()]
    assert [c.state_path for c in second] == ["a", "b"]
    assert second[1].edge_hold_ns < 5 * MS  # held from its own arrival, not from path a's
    assert mpc.counters.copies == 2
    assert mpc.counters.commands == 2  # two solves for two States
