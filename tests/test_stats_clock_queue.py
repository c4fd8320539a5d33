from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dynqos.common.clock import FakeClock, MonotonicClock, seconds, to_ns
from dynqos.common.queues import BoundedQueue, PendingChanges
from dynqos.common.stats import Ema, SlidingWindow, percentile

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@given(size=st.integers(1, 60), samples=st.lists(finite, max_size=300))
def test_window_mean_and_percentiles_match_numpy_on_the_last_samples(size: int, samples: list[float]) -> None:
    window = SlidingWindow(size)
    window.extend(samples)
    tail = samples[-size:]
    assert len(window) == len(tail)
    if not tail:
        assert window.mean() is None
        assert window.percentile(50) is None
        return
    assert window.mean() == pytest.approx(float(np.mean(tail)), rel=1e-9, abs=1e-6)
    for q in (0, 50, 99, 100):
        assert window.percentile(q) == pytest.approx(float(np.percentile(tail, q)), rel=1e-9, abs=1e-6)


def test_window_stays_exact_over_a_long_run() -> None:
    window = SlidingWindow(10)
    for i in range(100_000):
        window.push(1e6 if i % 2 else 1e-3)
    window.extend([5.0] * 10)
    assert window.mean() == pytest.approx(5.0, abs=1e-9)
    assert window.full


def test_window_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="size"):
        SlidingWindow(0)
    window = SlidingWindow(3)
    with pytest.raises(ValueError, match="finite"):
        window.push(math.nan)
    with pytest.raises(ValueError, match="percentile"):
        window.percentile(101)
    with pytest.raises(ValueError, match="no samples"):
        percentile([], 50)
    window.push(1.0)
    window.clear()
    assert window.mean() is None
    assert window.values() == []


def test_ema_follows_the_papers_filter() -> None:
    ema = Ema(0.8, 0.2)
    assert ema.value is None
    assert ema.update(10.0) == 10.0  # first sample initialises
    assert ema.update(0.0) == pytest.approx(8.0)
    assert ema.update(0.0) == pytest.approx(6.4)
    ema.reset()
    assert ema.value is None
    assert Ema(0.5).b == 0.5
    with pytest.raises(ValueError, match="a must"):
        Ema(1.0)
    with pytest.raises(ValueError, match="b must"):
        Ema(0.5, 0.0)
    with pytest.raises(ValueError, match="finite"):
        Ema(0.5).update(math.inf)


def test_clocks() -> None:
    clock = FakeClock(5)
    assert clock.now_ns() == 5
    clock.advance_s(0.5)
    assert clock.now_ns() == 500_000_005
    with pytest.raises(ValueError, match="back"):
        clock.advance_ns(-1)
    with pytest.raises(ValueError, match="start_ns"):
        FakeClock(-1)
    real = MonotonicClock()
    assert real.now_ns() <= real.now_ns()
    assert seconds(to_ns(1.25)) == 1.25


def test_queue_drops_oldest_and_counts() -> None:
    queue: BoundedQueue[int] = BoundedQueue(3)
    for i in range(5):
        queue.put(i)
    assert queue.dropped == 2
    assert len(queue) == 3
    assert queue.get(0) == 2
    assert queue.drain() == [3, 4]
    assert queue.get_nowait() is None
    assert queue.get(timeout_s=0.01) is None
    with pytest.raises(ValueError, match="maxlen"):
        BoundedQueue(0)


def test_queue_wakes_a_waiting_consumer() -> None:
    queue: BoundedQueue[str] = BoundedQueue(1)
    got: list[str | None] = []
    consumer = threading.Thread(target=lambda: got.append(queue.get(timeout_s=10)))
    consumer.start()
    queue.put("hello")
    consumer.join(timeout=10)
    assert got == ["hello"]


def test_a_put_into_an_empty_queue_wakes_an_event_loop_once_and_its_drain_takes_all() -> None:
    import asyncio

    from dynqos.common.lifecycle import waker

    queue: BoundedQueue[int] = BoundedQueue(3)
    wakes: list[int] = []
    taken: list[list[int]] = []

    async def main() -> None:
        loop = asyncio.get_running_loop()

        def take() -> None:
            wakes.append(len(queue))
            taken.append(queue.drain())

        queue.wake = waker(loop, take)
        putter = threading.Thread(target=lambda: [queue.put(i) for i in range(5)])  # from a zenoh-like thread
        putter.start()
        putter.join()  # the loop is held meanwhile: the drain it was woken for waits its turn
        await asyncio.sleep(0)  # the scheduled drain runs (a loop turn, not a wait for time)
        queue.put(5)  # empty again: wakes again
        await asyncio.sleep(0)

    asyncio.run(main())
    assert taken == [[2, 3, 4], [5]]  # bounded: the oldest two dropped and counted
    assert queue.dropped == 2
    assert wakes == [3, 1]  # one wake per empty-to-waiting, not one per item
    queue.put(6)  # the loop has closed: the wake does nothing, the item waits
    assert queue.drain() == [6]


def test_pending_changes_keep_the_newest_per_key_and_refuse_a_flood_of_new_keys() -> None:
    pending: PendingChanges[str] = PendingChanges(2)
    assert pending.offer("a", True) is True  # the first waiting change: wake the worker
    assert pending.offer("a", False) is False  # the same key again: the newest wins, no new wake-up
    assert pending.offer("b", True) is False
    assert pending.offer("c", True) is None  # a third key while two wait: refused and counted
    assert pending.offer("b", False) is False  # a waiting key is still updated
    assert pending.refused == 1
    assert pending.take() == {"a": False, "b": False}
    assert pending.take() == {}
    assert pending.offer("c", True) is True  # room again
