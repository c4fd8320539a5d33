"""A user's task at the edge (edge/tasks.py) on a MemoryBus and a fake clock: what its handler does
wrong stays in its task. Each failure kind is shown both ways: the service counts it, says it once and
goes on serving, where the bare handler, called as the service calls it, would have stopped it."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any

import msgspec
import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Received
from dynqos.common.clock import FakeClock
from dynqos.common.config import Config
from dynqos.common.messages import TaskAnswer, TaskRequest
from dynqos.common.queues import BoundedQueue
from dynqos.common.tasks import Codec, Edge, Task
from dynqos.edge.runtime import Ports
from dynqos.edge.tasks import HANG_MIN_S, MAX_ABANDONED, TaskService, _Worker
from tests.edge_cores import take


class Ask(msgspec.Struct):
    x: float


class Say(msgspec.Struct):
    y: float


TASK = Task("twice", request=Ask, answer=Say, rate_hz=10, deadline_s=0.1)
CODEC: Codec[Ask, Say] = Codec(TASK)


class Rig:
    def __init__(self, handle: Callable[[Ask], Any]) -> None:
        self.clock = FakeClock(1_000_000_000)
        self.bus = MemoryBus(self.clock)
        self.answers: BoundedQueue[Received] = BoundedQueue(64)
        self.bus.subscribe(f"{keys.ROOT}/*/down/task/twice", self.answers, expect=(TaskAnswer,))
        self.service = TaskService(Edge(TASK, handle), Config(), Ports(self.bus, self.clock), replica="r1")
        self.seq = 0

    def ask(self, x: float, uav: str = "uav1", budget_ms: float = 100.0) -> None:
        self.seq += 1
        request = TaskRequest(
            uav=uav,
            seq=self.seq,
            task="twice",
            stamp_ns=0,
            budget_ms=budget_ms,
            body=CODEC.encode_request(Ask(x)),
        )
        self.bus.publisher(keys.task_uplink(uav, keys.Flow.DEFAULT, "twice"), 5).put(request)  # type: ignore[arg-type]
        take(self.service, self.clock.now_ns())

    def serve(self) -> None:
        """What the worker does with the next request (no thread: the test is the worker)."""
        item = self.service.next_request()
        assert item is not None
        self.service.serve_one(item, _Worker(1))

    def said(self) -> list[float]:
        out = []
        for item in self.answers.drain():
            assert isinstance(item.message, TaskAnswer)
            out.append(CODEC.decode_answer(item.message.body).y)
        return out


def twice(ask: Ask) -> Say:
    if ask.x < 0:
        raise ValueError("negative")
    return Say(2 * ask.x)


def test_a_request_is_answered_with_the_handlers_answer_on_its_drones_key() -> None:
    rig = Rig(twice)
    rig.ask(3.0)
    rig.serve()
    assert rig.said() == [6.0]
    assert rig.service.counters["answers"] == 1


def test_a_handler_that_raises_is_counted_said_once_and_the_next_request_is_served(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with pytest.raises(ValueError, match="negative"):
        twice(Ask(-1.0))  # without the service: the call raises out of the worker
    rig = Rig(twice)
    with caplog.at_level(logging.WARNING):
        for x in (-1.0, -2.0, 4.0):
            rig.ask(x)
            rig.serve()
    assert rig.said() == [8.0]
    assert rig.service.counters["raised"] == 2
    lines = [r.getMessage() for r in caplog.records if "raised" in r.getMessage()]
    assert len(lines) == 1
    assert "task-twice" in lines[0]
    assert "ValueError: negative" in lines[0]


@pytest.mark.parametrize("junk", [{"y": "six"}, "six", None, Ask(1.0), {"z": 1.0}])
def test_a_handler_that_returns_junk_sends_nothing(junk: object) -> None:
    with pytest.raises(Exception, match=r"Expected|missing"):
        CODEC.decode_answer(msgspec.msgpack.encode(junk))  # the drone would refuse it
    rig = Rig(lambda ask: junk)
    rig.ask(1.0)
    rig.serve()
    assert rig.said() == []
    assert rig.service.counters["bad_answers"] == 1


def test_a_slow_handler_answer_past_the_budget_is_not_sent() -> None:
    rig = Rig(lambda ask: (rig.clock.advance_ns(150_000_000), Say(ask.x))[1])
    rig.ask(1.0, budget_ms=100.0)
    rig.serve()
    rig.ask(2.0, budget_ms=200.0)
    rig.serve()
    assert rig.said() == [2.0]
    assert rig.service.counters["late"] == 1


def test_a_request_that_waited_past_its_budget_is_dropped_unread() -> None:
    called: list[float] = []
    rig = Rig(lambda ask: (called.append(ask.x), Say(ask.x))[1])
    rig.ask(1.0, budget_ms=50.0)
    rig.clock.advance_ns(60_000_000)
    rig.serve()
    assert called == []
    assert rig.said() == []
    assert rig.service.counters["expired"] == 1


def test_a_newer_request_of_a_drone_replaces_the_one_not_yet_served() -> None:
    rig = Rig(twice)
    rig.ask(1.0)
    rig.ask(2.0)
    rig.serve()
    assert rig.said() == [4.0]
    assert rig.service.counters["superseded"] == 1
    assert rig.service.next_request() is None


def test_a_request_body_that_is_not_the_tasks_type_is_counted() -> None:
    rig = Rig(twice)
    request = TaskRequest(
        uav="uav1", seq=1, task="twice", stamp_ns=0, budget_ms=100, body=b"\x93\x01\x02\x03"
    )
    rig.bus.publisher(keys.task_uplink("uav1", keys.Flow.DEFAULT, "twice"), 5).put(request)  # type: ignore[arg-type]
    take(rig.service, rig.clock.now_ns())
    rig.serve()
    assert rig.said() == []
    assert rig.service.counters["bad_requests"] == 1


def test_a_hung_handler_is_left_behind_and_a_new_worker_serves_the_other_drones() -> None:
    """With real worker threads: the first call hangs; past the hang bound the tick leaves that worker
    behind and the next drone's request is answered. Without the watchdog (no tick), it never is."""
    release = threading.Event()

    def hangs_for_uav1(ask: Ask) -> Say:
        if ask.x == 1.0:
            release.wait(30)
        return Say(2 * ask.x)

    for watched in (False, True):
        _hang_once(hangs_for_uav1, release, watched)


def _hang_once(handle: Callable[[Ask], Say], release: threading.Event, watched: bool) -> None:
    release.clear()
    rig = Rig(handle)
    rig.service._start_worker()
    try:
        rig.ask(1.0, uav="uav1", budget_ms=5000)
        assert _until(lambda: rig.service._workers[0].busy_since_ns is not None)
        rig.ask(5.0, uav="uav2", budget_ms=5000)
        if watched:
            rig.clock.advance_ns(int(HANG_MIN_S * 1e9) + 1)
            rig.service.tick(rig.clock.now_ns())
        answered = _until(lambda: len(rig.answers) > 0, timeout_s=1.0 if not watched else 5.0)
        assert answered is watched
        if watched:
            assert rig.said() == [10.0]
            assert rig.service.counters["hung"] == 1
            assert "serving=yes" in rig.service.health()
    finally:
        release.set()
        rig.service._running = False


def test_after_max_abandoned_hung_workers_the_service_says_it_serves_no_more() -> None:
    rig = Rig(twice)
    for _ in range(MAX_ABANDONED):
        worker = _Worker(0, busy_since_ns=rig.clock.now_ns(), call="a call")
        rig.service._workers.append(worker)
        rig.clock.advance_ns(int(HANG_MIN_S * 1e9) + 1)
        rig.service.tick(rig.clock.now_ns())
    rig.service._running = False
    assert rig.service.counters["hung"] == MAX_ABANDONED
    assert "serving=no (hung)" in rig.service.health()


def _until(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    done = threading.Event()
    deadline = threading.Timer(timeout_s, done.set)
    deadline.start()
    try:
        while not done.is_set():
            if condition():
                return True
            done.wait(0.005)
        return condition()
    finally:
        deadline.cancel()
