"""The drone's shell of its tasks (onboard/task_runner.py) on a MemoryBus: the user's onboard code runs
on its task's thread, so whatever it does (raise, return junk, hang) the tick hands out its jobs at once
and goes on; each failure is counted and said once, and a request goes out on the flow the core named."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec
import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Received
from dynqos.common.clock import MonotonicClock
from dynqos.common.messages import TaskRequest
from dynqos.common.modes import Flow
from dynqos.common.queues import BoundedQueue
from dynqos.common.tasks import Drone, Onboard, Steer, Task
from dynqos.onboard.fc import FcState
from dynqos.onboard.links import PathLink
from dynqos.onboard.task_runner import JOBS_WAITING, TaskRunner, TaskThread
from dynqos.onboard.tasks import TaskJobs


class Q(msgspec.Struct):
    x: float


TASK = Task("probe", request=Q, answer=Q, rate_hz=10, deadline_s=0.1)
FC = FcState(0, (1.0, 2.0, -1.5), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))


def _runner(
    request: Callable[[Drone], Any], fallback: Callable[[Drone], Any] = lambda d: Steer(0.5)
) -> tuple[TaskRunner, threading.Event, BoundedQueue[Received]]:
    stop = threading.Event()
    onboard = Onboard(TASK, request=request, apply=lambda a, d: Steer(a.x), fallback=fallback)
    runner = TaskRunner("uav1", [onboard], MonotonicClock(), stop)
    bus = MemoryBus()
    edge: BoundedQueue[Received] = BoundedQueue(64)
    bus.subscribe(keys.task_uplink_all_drones("probe"), edge, expect=(TaskRequest,))
    runner.open(PathLink("", bus))
    runner.start()
    return runner, stop, edge


def _reports(
    runner: TaskRunner, wanted: Callable[[list[Any], list[Any]], bool]
) -> tuple[list[Any], list[Any]]:
    """The threads' reports, gathered until `wanted` holds (the reports are what the test awaits)."""
    sent: list[Any] = []
    steers: list[Any] = []
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and not wanted(sent, steers):
        new_sent, new_steers = runner.reports()
        sent += new_sent
        steers += new_steers
        threading.Event().wait(0.005)
    return sent, steers


def test_a_request_is_built_on_the_tasks_thread_and_sent_on_the_flow_the_core_named() -> None:
    runner, stop, edge = _runner(lambda d: Q(d.pos_m[0]))
    try:
        runner.hand_out(TaskJobs(requests=(("probe", 1, Flow.PRIORITY),)), FC, True)
        sent, _ = _reports(runner, lambda s, _: bool(s))
        assert [(s.seq, s.sent_ns is not None) for s in sent] == [(1, True)]
        item = edge.get(5)
        assert item is not None
        assert item.key == keys.task_uplink("uav1", Flow.PRIORITY, "probe")
    finally:
        stop.set()
        runner.join(2)


@pytest.mark.parametrize(
    ("request_fn", "kind"),
    [
        (lambda d: 1 / 0, "request_raised"),
        (lambda d: {"x": "not a number"}, "bad_request"),
    ],
)
def test_a_request_builder_that_raises_or_builds_junk_sends_nothing_and_is_said_once(
    caplog: pytest.LogCaptureFixture, request_fn: Callable[[Drone], Any], kind: str
) -> None:
    runner, stop, edge = _runner(request_fn)
    try:
        with caplog.at_level(logging.WARNING):
            for seq in (1, 2):
                runner.hand_out(TaskJobs(requests=(("probe", seq, Flow.DEFAULT),)), FC, True)
            sent, _ = _reports(runner, lambda s, _: len(s) == 2)
        assert [s.sent_ns for s in sent] == [None, None]  # skipped: the core counts them
        assert runner.threads["probe"].failures == {kind: 2}
        assert len([r for r in caplog.records if kind in r.getMessage()]) == 1
        assert edge.get_nowait() is None
    finally:
        stop.set()
        runner.join(2)


def test_a_fallback_that_returns_no_steer_leaves_the_flight_as_it_is() -> None:
    runner, stop, _ = _runner(lambda d: Q(0.0), fallback=lambda d: "turn left")
    try:
        runner.hand_out(TaskJobs(fallback=("probe",)), FC, True)
        _reports(runner, lambda s, t: bool(runner.threads["probe"].failures))
        assert runner.threads["probe"].failures == {"fallback_not_steer": 1}
        assert runner.reports()[1] == []
    finally:
        stop.set()
        runner.join(2)


def test_a_hung_onboard_side_never_holds_the_tick_and_its_jobs_stay_bounded() -> None:
    """Without its own thread the hand-out would wait for the hung call; here 50 hand-outs take no time,
    the jobs waiting are bounded, the rest dropped and counted."""
    release = threading.Event()
    runner, stop, _ = _runner(lambda d: release.wait(30))
    thread: TaskThread = runner.threads["probe"]
    try:
        runner.hand_out(TaskJobs(requests=(("probe", 1, Flow.DEFAULT),)), FC, True)
        _reports(runner, lambda s, t: thread.busy_since_ns is not None)
        started = time.perf_counter()
        for seq in range(2, 52):
            runner.hand_out(TaskJobs(requests=(("probe", seq, Flow.DEFAULT),)), FC, True)
        assert time.perf_counter() - started < 0.5
        assert len(thread.jobs) == JOBS_WAITING
        assert thread.jobs.dropped == 50 - JOBS_WAITING
    finally:
        release.set()
        stop.set()
        runner.join(2)
