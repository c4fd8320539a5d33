"""The cell's pure parts: scheduler shares, capacity bucket, virtual users, delay line, UE buffer, traces."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dynqos.sim.network.delayline import DelayLine
from dynqos.sim.network.scheduler import CapacityBucket, VirtualUser, weighted_fair_share
from dynqos.sim.network.traces import PACKET_BITS, Trace, TraceError
from dynqos.sim.network.uebuffer import UeBuffer

TTI = 1_000_000


def test_backlogged_users_share_by_weight() -> None:
    alloc = weighted_fair_share(100.0, {"drone": 1e9, "bg": 1e9}, {"drone": 4, "bg": 1})
    assert alloc == pytest.approx({"drone": 80.0, "bg": 20.0})
    alloc = weighted_fair_share(90.0, {"a": 1e9, "b": 1e9, "c": 1e9}, {"a": 1, "b": 1, "c": 1})
    assert alloc == pytest.approx({"a": 30.0, "b": 30.0, "c": 30.0})


def test_an_idle_users_share_goes_to_the_others() -> None:
    alloc = weighted_fair_share(100.0, {"drone": 0.0, "bg": 1e9}, {"drone": 4, "bg": 1})
    assert alloc == pytest.approx({"drone": 0.0, "bg": 100.0})
    alloc = weighted_fair_share(
        100.0, {"drone": 10.0, "bg": 1e9, "bg2": 1e9}, {"drone": 4, "bg": 1, "bg2": 3}
    )
    assert alloc["drone"] == pytest.approx(10.0)
    assert alloc["bg"] == pytest.approx(22.5)
    assert alloc["bg2"] == pytest.approx(67.5)


@given(
    capacity=st.floats(0, 1e6),
    users=st.dictionaries(
        st.text("abcdef", min_size=1, max_size=3),
        st.tuples(st.floats(0, 1e6), st.floats(0.1, 10)),
        min_size=1,
        max_size=6,
    ),
)
def test_allocation_is_feasible_work_conserving_and_weighted(
    capacity: float, users: dict[str, tuple[float, float]]
) -> None:
    demands = {k: d for k, (d, _) in users.items()}
    weights = {k: w for k, (_, w) in users.items()}
    alloc = weighted_fair_share(capacity, demands, weights)
    total = sum(alloc.values())
    assert total <= capacity * (1 + 1e-9) + 1e-6
    for name in users:
        assert -1e-9 <= alloc[name] <= demands[name] * (1 + 1e-9) + 1e-6
    # Work-conserving: capacity is left over only when every demand is met.
    if total < capacity - 1e-6 * max(1.0, capacity):
        assert all(alloc[n] == pytest.approx(demands[n], rel=1e-6, abs=1e-6) for n in users)
    # Weighted: two unsatisfied users get shares in proportion to their weights.
    unsatisfied = [n for n in users if alloc[n] < demands[n] - 1e-6 * max(1.0, demands[n])]
    for a in unsatisfied:
        for b in unsatisfied:
            assert alloc[a] / weights[a] == pytest.approx(alloc[b] / weights[b], rel=1e-6, abs=1e-6)


def test_share_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="capacity"):
        weighted_fair_share(-1.0, {"a": 1.0}, {"a": 1.0})
    with pytest.raises(ValueError, match="weight"):
        weighted_fair_share(1.0, {"a": 1.0}, {"a": 0.0})


def test_bucket_releases_rate_times_elapsed_and_caps_stalls() -> None:
    bucket = CapacityBucket(TTI, max_ticks=20)
    assert bucket.release(1e6, 0) == 0.0
    assert bucket.release(1e6, 3 * TTI) == pytest.approx(3000.0)  # a late timer loses nothing
    assert bucket.release(1e6, 3 * TTI + 500 * TTI) == pytest.approx(20_000.0)  # a stall: capped
    with pytest.raises(ValueError, match="tti"):
        CapacityBucket(0)


def test_the_papers_table_ii_physics_in_the_fluid_model() -> None:
    """47 Mbit/s drone + 80 Mbit/s background into 81.3 Mbit/s, 10 s of 1 ms TTIs."""
    for weight, drone_expect, bg_expect in ((1.0, 40.65, 40.65), (4.0, 47.0, 34.3)):
        bg = VirtualUser("bg", 1.0, 80e6)
        ue = UeBuffer(10**9)
        bucket = CapacityBucket(TTI)
        bucket.release(0, 0)
        delivered = 0.0
        delays = []
        for tick in range(1, 10_001):
            now = tick * TTI
            ue.append(b"x" * round(47e6 / 8 / 1000), now)
            bg.arrive(0.001)
            demands = {"d": ue.size * 8.0, "bg": bg.backlog_bits}
            alloc = weighted_fair_share(bucket.release(81.3e6, now), demands, {"d": weight, "bg": 1.0})
            delivered += len(ue.take(int(alloc["d"] // 8))) * 8
            bg.serve(alloc["bg"])
            if tick % 1000 == 0:
                delays.append((ue.head_age_ns(now) or 0) / 1e6)
        assert delivered / 10 / 1e6 == pytest.approx(drone_expect, rel=0.01)
        assert bg.delivered_bits / 10 / 1e6 == pytest.approx(bg_expect, rel=0.01)
        if weight == 1.0:
            assert delays[-1] > delays[4] > delays[0]  # the queue grows without bound
        else:
            assert max(delays) <= 2.0  # stays within a TTI or two


def test_queue_delay_is_buffer_over_service_rate_in_steady_state() -> None:
    """A standing queue of 1 Mbit served at 10 Mbit/s while 10 Mbit/s arrives: 100 ms of delay."""
    ue = UeBuffer(10**8)
    ue.append(b"x" * 125_000, 0)  # 1 Mbit standing queue
    bucket = CapacityBucket(TTI)
    bucket.release(0, 0)
    for tick in range(1, 3001):
        now = tick * TTI
        ue.append(b"x" * 1250, now)  # 10 Mbit/s
        alloc = weighted_fair_share(bucket.release(10e6, now), {"d": ue.size * 8.0}, {"d": 1.0})
        ue.take(int(alloc["d"] // 8))
    assert ue.size == pytest.approx(125_000, abs=1250)
    assert (ue.head_age_ns(3000 * TTI) or 0) / 1e6 == pytest.approx(ue.size * 8 / 10e6 * 1000, rel=0.02)


def test_virtual_user_backlog_is_bounded() -> None:
    user = VirtualUser("bg", 1.0, 80e6, max_backlog_s=0.5)
    for _ in range(100):
        user.arrive(0.1)
    assert user.backlog_bits == pytest.approx(40e6)
    user.serve(1e9)
    assert user.backlog_bits == 0.0
    assert user.delivered_bits == pytest.approx(40e6)


def test_delay_line_keeps_order_and_delays() -> None:
    line: DelayLine[str] = DelayLine(10 * TTI, jitter_ns=5 * TTI, seed=3)
    dues = [line.push(str(i), 100, i * TTI) for i in range(50)]
    assert dues == sorted(dues)
    assert all(due >= i * TTI + 5 * TTI for i, due in enumerate(dues))
    assert line.size == 5000
    assert line.next_due_ns() == dues[0]
    assert line.pop_due(dues[0] - 1) == []
    out = line.pop_due(10**12)
    assert out == [str(i) for i in range(50)]
    assert line.size == 0
    assert line.next_due_ns() is None
    line.push("x", 7, 0)
    assert line.clear() == 7
    with pytest.raises(ValueError, match="delays"):
        DelayLine(-1)


def test_ue_buffer_bounds_and_ages() -> None:
    ue = UeBuffer(10)
    ue.append(b"abcd", 0)
    ue.append(b"efgh", 5)
    assert ue.free == 2
    with pytest.raises(OverflowError):
        ue.append(b"xyz", 6)
    assert ue.take(3) == b"abc"
    assert ue.head_age_ns(10) == 10
    assert ue.take(2) == b"de"
    assert ue.head_age_ns(10) == 5
    assert ue.take(100) == b"fgh"
    assert ue.head_age_ns(10) is None
    ue.append(b"z", 1)
    assert ue.clear() == 1
    with pytest.raises(ValueError, match="capacity"):
        UeBuffer(0)


def test_trace_capacity(tmp_path: Path) -> None:
    path = tmp_path / "t.up"
    path.write_text("\n".join(["1", "1", "2", "4"]) + "\n")  # 4 packets every 4 ms
    trace = Trace.load(path)
    assert trace.mean_mbps() == pytest.approx(4 * PACKET_BITS / 0.004 / 1e6)
    assert trace.bits_between(0.0, 0.004) == 4 * PACKET_BITS
    assert trace.bits_between(0.004, 0.012) == 8 * PACKET_BITS  # it repeats
    assert trace.bits_between(0.0015, 0.0025) == PACKET_BITS
    assert trace.bits_between(0.003, 0.003) == 0.0
    scaled = Trace.load(path, mean_mbps=6.0)
    assert scaled.mean_mbps() == pytest.approx(6.0)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("", "no delivery"),
        ("5\n3\n", "must not decrease"),
        ("a\n", "not a Mahimahi"),
        ("-1\n", "negative"),
    ],
)
def test_bad_traces(tmp_path: Path, text: str, reason: str) -> None:
    path = tmp_path / "bad.up"
    path.write_text(text)
    with pytest.raises(TraceError, match=reason):
        Trace.load(path)
    with pytest.raises(TraceError, match="cannot read"):
        Trace.load(tmp_path / "missing.up")
    with pytest.raises(TraceError, match="scale"):
        Trace([1], scale=0)


def test_real_cellular_traces_load(shared_data: Path) -> None:
    for name in ("ATT-LTE-driving-2016.up", "TMobile-LTE-short.up", "Verizon-LTE-short.up"):
        trace = Trace.load(shared_data / "traces" / name)
        assert 0.1 < trace.mean_mbps() < 200
        scaled = Trace.load(shared_data / "traces" / name, mean_mbps=81.3)
        assert scaled.bits_between(0, scaled.period_ms / 1000) / (
            scaled.period_ms / 1000
        ) / 1e6 == pytest.approx(81.3, rel=1e-6)
