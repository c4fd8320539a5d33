"""Edge replicas subscribe to the drones they fly or stand by for, found by the drones' presence tokens
(edge/feeds.py), and to no other: the wiring of the MPC and planner services on the in-memory bus (the
same codec and checks as zenoh) with a fake clock. Over zenoh: tests/test_edge_services.py."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority
from dynqos.common.clock import FakeClock
from dynqos.common.config import load_config
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import State
from dynqos.edge import feeds
from dynqos.edge.mpc.service import MpcService
from dynqos.edge.planner.service import PlannerService
from dynqos.edge.replicas import ranked
from dynqos.edge.runtime import Ports
from tests.edge_cores import take, turn

DRONES = [f"uav{i}" for i in range(12)]
Service = MpcService | PlannerService


def _mpc(name: str, bus: MemoryBus, clock: FakeClock) -> Service:
    return MpcService(load_config(None, [f'mpc.replica_id="{name}"']), Ports(bus, clock))


def _planner(name: str, bus: MemoryBus, clock: FakeClock) -> Service:
    return PlannerService(load_config(None, [f'planner.replica_id="{name}"']), Ports(bus, clock))


def _settle(services: list[Service]) -> None:
    for service in services:
        if isinstance(service, MpcService):
            turn(service, service.clock.now_ns())
        else:  # its tick publishes at publish_hz; what it follows is decided here
            take(service, service.clock.now_ns())
            service.discover(service.clock.now_ns())


def _state(uav: str, seq: int, clock: FakeClock) -> State:
    return State(uav=uav, seq=seq, stamp_ns=clock.now_ns(), pos_m=(0.0, 0.0, -1.5),
                 vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0))  # fmt: skip


def _followers(uav: str, live: set[str]) -> set[str]:
    return set(ranked(uav, live)[:2])


@pytest.mark.parametrize("make", [_mpc, _planner], ids=["mpc", "planner"])
def test_each_replica_follows_only_the_drones_it_flies_or_stands_by_for(
    make: Callable[[str, MemoryBus, FakeClock], Service],
) -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    tokens = {uav: bus.declare_token(keys.drone_presence(uav)) for uav in DRONES}
    services = [make(name, bus, clock) for name in ("r-a", "r-b", "r-c")]
    _settle(services)
    live = {s.replica for s in services}
    for service in services:
        expected = {uav for uav in DRONES if service.replica in _followers(uav, live)}
        assert service.feeds.subscribed == expected
        assert 0 < len(expected) < len(DRONES)  # three replicas: each follows some, none all

    # Every drone's state reaches its two followers and nobody else: nothing is decoded to be dropped
    # (an MPC standby reads it from zenoh's newest-only slot, twice a second: edge/mpc/service.py).
    publishers = {uav: bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
                  for uav in DRONES}  # fmt: skip
    for uav, pub in publishers.items():
        pub.put(_state(uav, 1, clock))
    for _ in range(50):  # half a second of 10 ms turns: an MPC standby reads the newest state by then
        _settle(services)
        clock.advance_s(0.01)
    received = [s.feeds.feeds[0].stats.received for s in services]
    assert received == [len(s.feeds.subscribed) for s in services]
    assert sum(received) == 2 * len(DRONES)
    for service in services:
        if isinstance(service, MpcService):
            assert service.counters.not_mine == 0
            assert service.counters.states == len(service.feeds.subscribed)

    # A replica goes: the two left follow every drone (each is primary or standby for all of them).
    gone = services.pop()
    gone.membership.token.close()
    _settle(services)
    for service in services:
        assert service.feeds.subscribed == set(DRONES)

    # A drone goes (its daemon's session closed): nobody follows it, its states reach nobody.
    tokens.pop("uav3").close()
    _settle(services)
    before = [s.feeds.feeds[0].stats.received for s in services]
    publishers["uav3"].put(_state("uav3", 2, clock))
    _settle(services)
    assert all("uav3" not in s.feeds.subscribed for s in services)
    assert [s.feeds.feeds[0].stats.received for s in services] == before

    # It comes back (the session reconnected): followed again.
    tokens["uav3"] = bus.declare_token(keys.drone_presence("uav3"))
    _settle(services)
    assert all("uav3" in s.feeds.subscribed for s in services)


def test_a_drone_that_never_announces_itself_is_not_served() -> None:
    """The cost of following by token: a drone without one (not started by `dynqos onboard`) gets no
    command; the docs say so."""
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    mpc = _mpc("r-a", bus, clock)
    bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME).put(
        _state("uav1", 1, clock)
    )
    turn(mpc, clock.now_ns())
    assert mpc.counters.states == 0
    assert mpc.counters.commands == 0
    bus.declare_token(keys.drone_presence("uav1"))
    turn(mpc, clock.now_ns())  # follows it from now on
    bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME).put(
        _state("uav1", 2, clock)
    )
    turn(mpc, clock.now_ns())
    assert mpc.counters.commands == 1


def test_bad_and_flooding_presence_tokens_are_refused_and_counted(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(feeds, "MAX_DRONES", 20)
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    mpc = _mpc("r-a", bus, clock)
    bus.declare_token("dynqos/edge/alive")  # "edge" is never a drone
    bus.declare_token(f"dynqos/{'x' * 33}/alive")  # too long for a drone id
    for i in range(30):
        bus.declare_token(keys.drone_presence(f"d{i}"))
    turn(mpc, clock.now_ns())
    assert len(mpc.feeds.subscribed) == 20
    assert "edge" not in mpc.feeds.subscribed
    assert mpc.feeds.refused == 2 + 10
