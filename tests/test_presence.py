"""edge/presence.py, on the in-memory bus: the one place the edge watches liveliness tokens."""

from __future__ import annotations

from typing import Any

from dynqos.common import keys
from dynqos.common.bus import MemoryBus
from dynqos.common.clock import FakeClock
from dynqos.edge.presence import Presence, Seen, Watch


def _replicas(bus: MemoryBus, pending_limit: int = 64, **kwargs: Any) -> Presence:
    watch = Watch("member", keys.replicas_of("mpc", "all"), keys.replica_of_token)
    return Presence(bus, "test", [watch], pending_limit=pending_limit, **kwargs)


def test_comings_and_goings_are_handed_over_once_each_and_our_own_never() -> None:
    bus = MemoryBus(FakeClock(0))
    woken: list[int] = []
    presence = _replicas(bus, me="a", wake=lambda: woken.append(1))
    a = bus.declare_token(keys.replica_token("mpc", "all", "a"))
    b = bus.declare_token(keys.replica_token("mpc", "all", "b"))
    assert woken == [1]  # once per batch: the first change of the batch wakes the consumer
    assert presence.take() == [Seen("member", "b", True)]
    assert presence.take() == []
    b.close()
    a.close()
    c = bus.declare_token(keys.replica_token("mpc", "all", "c"))
    c.close()  # came and went before the consumer looked: the newest word wins, nothing changed
    assert presence.take() == [Seen("member", "b", False)]
    assert presence.present["member"] == set()
    assert len(woken) == 2


def test_invalid_names_and_those_beyond_the_cap_are_refused_and_counted() -> None:
    bus = MemoryBus(FakeClock(0))
    presence = _replicas(bus, valid=keys.valid_replica_id, cap=3)
    for name in ("bad name", "ok1", "ok2", "ok3", "ok4"):
        bus.declare_token(keys.replica_token("mpc", "all", name))
    assert [s.name for s in presence.take()] == ["ok1", "ok2", "ok3"]
    assert presence.refused == 2


def test_a_flood_beyond_the_pending_bound_is_refused_and_counted() -> None:
    bus = MemoryBus(FakeClock(0))
    presence = _replicas(bus, pending_limit=10)
    for i in range(15):
        bus.declare_token(keys.replica_token("mpc", "all", f"r{i}"))
    assert len(presence.take()) == 10
    assert presence.refused == 5


def test_names_left_to_the_consumer_pass_through() -> None:
    bus = MemoryBus(FakeClock(0))
    presence = _replicas(bus)
    bus.declare_token(keys.replica_token("mpc", "all", "bad name"))
    assert presence.take() == [Seen("member", "bad name", True)]  # Assignment refuses it, and counts it
    assert presence.refused == 0


def test_the_live_set_is_asked_for_at_start() -> None:
    bus = MemoryBus(FakeClock(0))
    bus.declare_token(keys.replica_token("mpc", "all", "early"))
    presence = _replicas(bus)
    presence.query(timeout_s=0.1)
    assert presence.take() == [Seen("member", "early", True)]
