"""The cell's radio (sim/network/cell_core.py) stepped TTI by TTI on a made-up clock: capacity, the
share between bearers and background users, traces, coverage and downlink loss, the QoD weight, and
the timeline of events. No process, no socket, no sleep."""

from __future__ import annotations

import pytest

from dynqos.common.config import BackgroundConfig, CellConfig, CellEventConfig
from dynqos.common.errors import ConfigError
from dynqos.sim.network.cell_core import CellCore, Effect, describe
from dynqos.sim.network.traces import PACKET_BITS, Trace

MS = 1_000_000
S = 1000 * MS
BEARERS = {"uav1-default": 1.0, "uav1-priority": 4.0}


def core(**cell: object) -> CellCore:
    config = CellConfig(**{"uplink_mbps": 10.0, "tti_ms": 1.0, **cell})  # type: ignore[arg-type]
    return CellCore(config, BEARERS, 0, ue_bearers=frozenset({"uav1-priority"}))


def run(c: CellCore, demands: dict[str, float], start_ms: int, ms: int) -> dict[str, float]:
    """`ms` TTIs from `start_ms` with the same demand each TTI; the bits each bearer was granted."""
    total = dict.fromkeys(demands, 0.0)
    for t in range(start_ms + 1, start_ms + ms + 1):
        grants = c.step(t * MS, demands)
        for name in demands:
            total[name] += grants[name]
    return total


def test_a_tti_grants_the_rate_times_the_tti_shared_by_weight() -> None:
    c = core()
    assert set(c.step(0, {"uav1-default": 1e6, "uav1-priority": 1e6}).values()) == {0.0}  # the first primes
    grants = c.step(1 * MS, {"uav1-default": 1e6, "uav1-priority": 1e6})  # one TTI after the first
    assert sum(grants.values()) == pytest.approx(10e6 * 1e-3)
    assert grants["uav1-priority"] == pytest.approx(4 * grants["uav1-default"])
    idle = c.step(2 * MS, {"uav1-default": 0.0, "uav1-priority": 0.0})
    assert (idle["uav1-default"], idle["uav1-priority"]) == (0.0, 0.0)


def test_background_users_take_their_share_and_an_event_changes_their_rate() -> None:
    c = core(
        background=(BackgroundConfig(name="bg", weight=1.0, offered_mbps=100.0),),
        events=(CellEventConfig(at_s=0.5, kind="background", user="bg", offered_mbps=0.0),),
    )
    loaded = run(c, {"uav1-default": 1e6, "uav1-priority": 0.0}, 0, 500)
    assert loaded["uav1-default"] == pytest.approx(0.5 * 10e6 * 0.5, rel=0.02)  # half, against the load
    assert c.due(499 * MS) == []
    (event,) = c.due(500 * MS)
    assert c.due(501 * MS) == []  # handed out once
    assert c.apply(event, 500 * MS) == Effect()
    assert c.background["bg"].backlog_bits == 0.0
    alone = run(c, {"uav1-default": 1e6, "uav1-priority": 0.0}, 500, 400)
    assert alone["uav1-default"] == pytest.approx(10e6 * 0.4, rel=0.02)


def test_coverage_loss_stops_the_uplink_and_the_downlink_for_its_duration() -> None:
    c = core()
    loss = CellEventConfig(at_s=0.0, kind="coverage_loss", duration_s=0.2, drop_connections=True)
    assert c.apply(loss, 100 * MS) == Effect(drop_bearers=("uav1-default", "uav1-priority"))
    assert not c.downlink_up(299 * MS)
    assert c.current_capacity_mbps(200 * MS) == 0.0
    lost = run(c, {"uav1-default": 1e9, "uav1-priority": 0.0}, 100, 199)
    assert lost["uav1-default"] == 0.0
    assert c.downlink_up(300 * MS)
    back = run(c, {"uav1-default": 1e9, "uav1-priority": 0.0}, 300, 100)
    assert back["uav1-default"] == pytest.approx(10e6 * 0.1, rel=0.05)  # no burst of saved-up capacity


def test_downlink_loss_leaves_the_uplink_alone() -> None:
    c = core()
    c.apply(CellEventConfig(at_s=0.0, kind="downlink_loss", duration_s=1.0), 0)
    assert not c.downlink_up(999 * MS)
    assert c.downlink_up(1 * S)
    assert run(c, {"uav1-default": 1e9, "uav1-priority": 0.0}, 0, 100)["uav1-default"] > 0


def test_a_trace_sets_the_capacity_and_a_capacity_event_ends_it() -> None:
    c = core(scale=2.0)
    c.set_trace(Trace([1, 2, 3, 4]), 0)  # four packets every 4 ms: 12 Mbit/s, halved by the scale
    granted = run(c, {"uav1-default": 1e9, "uav1-priority": 0.0}, 0, 400)
    assert granted["uav1-default"] == pytest.approx(100 * 4 * PACKET_BITS / 2, rel=0.02)
    assert c.capacity_bits_total == pytest.approx(granted["uav1-default"])  # all of it was wanted
    idle = c.capacity_bits_total
    run(c, {"uav1-default": 0.0, "uav1-priority": 0.0}, 400, 400)
    assert c.capacity_bits_total - idle == pytest.approx(idle, rel=0.02)  # counted whoever uses it
    assert c.apply(CellEventConfig(at_s=0.0, kind="trace", file="x.trace"), 0) == Effect(
        load_trace=("x.trace", 0.0)
    )  # the shell reads the file
    c.apply(CellEventConfig(at_s=0.0, kind="capacity", uplink_mbps=20.0), 400 * MS)
    assert c.trace is None
    assert c.current_capacity_mbps(400 * MS) == pytest.approx(10.0)  # 20 Mbit/s at scale 2


def test_a_drones_bearer_has_its_weight_only_while_a_qod_session_grants_it() -> None:
    c = core(qod=True)
    assert c.effective_weight("uav1-priority") == 1.0
    assert c.effective_weight("uav1-default") == 1.0
    c.grant("uav1-priority", True)
    assert c.effective_weight("uav1-priority") == 4.0
    c.apply(CellEventConfig(at_s=0.0, kind="weight", bearer="uav1-priority", weight=8.0), 0)
    assert c.effective_weight("uav1-priority") == 8.0
    assert c.apply(CellEventConfig(at_s=0.0, kind="qod_end", uav="uav1"), 0) == Effect(end_qod="uav1")
    c.qod = False  # no operator: weights as configured
    c.grant("uav1-priority", False)
    assert c.effective_weight("uav1-priority") == 8.0


@pytest.mark.parametrize(
    ("event", "key"),
    [
        (CellEventConfig(at_s=0.0, kind="background", user="nobody", offered_mbps=1.0), "user"),
        (CellEventConfig(at_s=0.0, kind="weight", bearer="nobody", weight=2.0), "bearer"),
        (CellEventConfig(at_s=0.0, kind="qod_end"), "kind"),
    ],
)
def test_an_event_naming_what_the_cell_does_not_have_is_a_config_error(
    event: CellEventConfig, key: str
) -> None:
    with pytest.raises(ConfigError, match=key):
        core().apply(event, 0)


def test_every_event_kind_is_described() -> None:
    events = [
        CellEventConfig(at_s=0.0, kind="background", user="bg", offered_mbps=80.0),
        CellEventConfig(at_s=0.0, kind="capacity", uplink_mbps=40.0),
        CellEventConfig(at_s=0.0, kind="trace"),
        CellEventConfig(at_s=0.0, kind="coverage_loss", duration_s=1.0, drop_connections=True),
        CellEventConfig(at_s=0.0, kind="downlink_loss", duration_s=1.0),
        CellEventConfig(at_s=0.0, kind="weight", bearer="uav1-priority", weight=2.0),
        CellEventConfig(at_s=0.0, kind="qod_end"),
    ]
    assert [describe(e) for e in events] == [
        "bg offers 80 Mbit/s", "uplink 40 Mbit/s", "trace (off)",
        "coverage lost for 1 s (connections dropped)",
        "downlink lost for 1 s (uplink unaffected)", "bearer uav1-priority weight 2",
        "the network ends the QoD sessions of every drone",
    ]  # fmt: skip
