"""The drone's side of its offloaded tasks on a fake clock (onboard/tasks.py), alone and in the onboard
core: when it calls, which answers apply, when the fallback flies and when the edge's answers fly again,
what the supervisor hears of it, and the heading a Steer sets."""

from __future__ import annotations

import logging
import math

import msgspec

from dynqos.common.config import Config
from dynqos.common.messages import TaskAnswer
from dynqos.common.modes import Flow
from dynqos.common.tasks import Steer, Task
from dynqos.onboard.core import SETPOINT_PERIOD_NS, OnboardCore
from dynqos.onboard.fc import AccelSetpoint, FcState
from dynqos.onboard.tasks import (
    OPEN_AFTER,
    RECOVER_AFTER,
    Mode,
    OnboardTasks,
    TaskSent,
    TaskSteer,
    TaskTimer,
    Verdict,
)
from dynqos.onboard.tick import TickInput

MS = 1_000_000


class Q(msgspec.Struct):
    x: float


CONTROL = Task("ctl", request=Q, answer=Q, rate_hz=10, deadline_s=0.05, flow="control")
BULK = Task("blk", request=Q, answer=Q, rate_hz=10, deadline_s=0.2, flow="bulk")
FLOWS = {"control": Flow.PRIORITY, "bulk": Flow.DEFAULT}


def answer(task: str, seq: int) -> TaskAnswer:
    return TaskAnswer(uav="uav1", seq=seq, task=task, stamp_ns=0, handle_ms=1.0, replica="r", body=b"\x80")


def test_a_request_is_due_once_a_period_and_a_bulk_tasks_stretches_with_the_camera_rate() -> None:
    control, bulk = TaskTimer(CONTROL, 0), TaskTimer(BULK, 0)
    due_control = [t for t in range(0, 1000 * MS, 10 * MS) if control.due(t) is not None]
    due_bulk = [t for t in range(0, 1000 * MS, 10 * MS) if bulk.due(t, rate_factor=0.5) is not None]
    assert len(due_control) == 10
    assert len(due_bulk) == 5  # throttled with the camera


def test_an_answer_applies_only_in_time_and_for_the_latest_request() -> None:
    timer = TaskTimer(CONTROL, 0)
    timer.sent(1, 0)
    timer.sent(2, 20 * MS)
    assert timer.answered(1, 30 * MS) is Verdict.STALE  # in time for request 1, but 2 is newer
    assert timer.answered(2, 80 * MS) is Verdict.LATE  # 60 ms > the 50 ms deadline
    timer.sent(3, 200 * MS)
    assert timer.answered(3, 230 * MS) is Verdict.APPLY
    assert timer.answered(3, 231 * MS) is Verdict.UNKNOWN  # a second copy
    assert timer.counts.applied == 1
    assert timer.counts.stale == 1
    assert timer.counts.late == 1


def test_the_deadline_is_enforced_by_the_clock_not_by_the_answer() -> None:
    timer = TaskTimer(CONTROL, 0)
    timer.sent(1, 0)
    assert not timer.expire(50 * MS)
    assert timer.mode is Mode.EDGE
    assert timer.expire(51 * MS)  # no answer yet, and none needed to know it is late
    assert timer.mode is Mode.FALLBACK
    assert timer.counts.misses == 1


def test_an_answer_after_its_miss_is_still_timed_for_the_supervisor_and_never_applied() -> None:
    timer = TaskTimer(CONTROL, 0)
    timer.sent(1, 0)
    assert timer.expire(60 * MS)
    assert timer.answered(1, 250 * MS) is Verdict.LATE
    assert timer.take_rtts() == [250.0]  # how late the calls come, not only the ones in time
    assert timer.counts.late == 1
    assert timer.counts.misses == 1
    assert timer.mode is Mode.FALLBACK


def test_one_answer_in_time_ends_a_lone_miss_and_an_open_circuit_needs_several() -> None:
    timer = TaskTimer(CONTROL, 0)
    t = 0
    timer.sent(1, t)
    timer.expire(t + 60 * MS)
    timer.sent(2, t + 100 * MS)
    assert timer.answered(2, t + 110 * MS) is Verdict.APPLY
    assert timer.mode is Mode.EDGE
    seq = 2
    for _ in range(OPEN_AFTER):  # misses in a row: the circuit opens
        seq += 1
        t += 100 * MS
        timer.sent(seq, t)
        timer.expire(t + 60 * MS)
    verdicts = []
    for _ in range(RECOVER_AFTER):
        seq += 1
        t += 100 * MS
        timer.sent(seq, t)
        verdicts.append(timer.answered(seq, t + 10 * MS))
    assert verdicts == [Verdict.RECOVERING] * (RECOVER_AFTER - 1) + [Verdict.APPLY]
    assert timer.mode is Mode.EDGE
    assert math.isclose(timer.fallback_s(t), 0.06 + 0.41 - 0.06 + 0.0, abs_tol=0.2)


def test_the_tasks_hand_out_requests_on_their_classes_flow_and_fallbacks_at_a_miss() -> None:
    tasks = OnboardTasks([CONTROL, BULK], 0)
    jobs, _ = tasks.tick(0, True, [], [], FLOWS, 1.0)
    assert jobs.requests == (("ctl", 1, Flow.PRIORITY), ("blk", 1, Flow.DEFAULT))
    jobs, said = tasks.tick(60 * MS, True, [], [TaskSent("ctl", 1, 0), TaskSent("blk", 1, None)], FLOWS, 1.0)
    assert jobs.fallback == ("ctl",)
    assert jobs.requests == ()
    assert said == [(logging.WARNING, "task ctl: no answer within 50 ms: fallback")]
    assert tasks.timers["blk"].counts.skipped == 1
    jobs, _ = tasks.tick(100 * MS, True, [], [], FLOWS, 1.0)
    assert jobs.fallback == ("ctl",)
    assert ("ctl", 2, Flow.PRIORITY) in jobs.requests
    jobs, said = tasks.tick(
        110 * MS, True, [(answer("ctl", 2), 110 * MS)], [TaskSent("ctl", 2, 100 * MS)], FLOWS, 1
    )
    assert [a.seq for a in jobs.apply] == [2]
    assert jobs.fallback == ()
    assert said == [(logging.INFO, "task ctl: answers in time again: the edge's answer applies")]


def test_nothing_is_asked_on_the_ground() -> None:
    tasks = OnboardTasks([CONTROL], 0)
    jobs, _ = tasks.tick(0, False, [], [], FLOWS, 1.0)
    assert jobs.requests == ()


def test_a_steer_applies_while_fresh_and_is_dropped_when_its_task_stops_answering() -> None:
    tasks = OnboardTasks([CONTROL], 0)
    assert tasks.steer([TaskSteer("ctl", Steer(1.0), 0)], 10 * MS) == 1.0
    assert tasks.steer([], 240 * MS) == 1.0  # two periods and a deadline: 250 ms
    assert tasks.steer([], 260 * MS) is None
    assert tasks.steer([TaskSteer("ctl", Steer(None), 300 * MS)], 300 * MS) is None


def _core(tasks: tuple[Task[object, object], ...]) -> OnboardCore:
    return OnboardCore(Config(), 0, tasks=tasks)


def _fc(now: int) -> FcState:
    return FcState(now, (0.0, 0.0, -1.5), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))


def test_in_the_core_a_steer_sets_the_setpoints_heading_and_a_control_tasks_calls_reach_the_supervisor() -> (
    None
):
    core = _core((CONTROL,))  # type: ignore[arg-type]
    now = 0
    out = core.tick(TickInput(now_ns=now, fc=_fc(now), offboard=True))
    state_flow = next(o.flow for o in out.publish if o.stream.value == "status")  # the flow after this step
    assert out.task_jobs.requests == (("ctl", 1, state_flow),)  # a control task rides the State's flow
    now += SETPOINT_PERIOD_NS
    sent = [TaskSent("ctl", 1, now)]
    core.tick(TickInput(now_ns=now, fc=_fc(now), task_sent=sent, offboard=True))
    assert core.tasks.timers["ctl"].oldest_outstanding_ms(now + 20 * MS) == 20.0
    now += SETPOINT_PERIOD_NS
    from dynqos.common.bus import Received

    arrived = Received("dynqos/uav1/down/task/ctl", answer("ctl", 1), now)
    steer = [TaskSteer("ctl", Steer(0.7), now)]
    out = core.tick(TickInput(now_ns=now, fc=_fc(now), downlink=[arrived], task_steers=steer, offboard=True))
    assert isinstance(out.setpoint, AccelSetpoint)
    assert out.setpoint.yaw_rad == 0.7
    assert [a.seq for a in out.task_jobs.apply] == [1]
    samples = core.tasks.take_samples(now)
    assert samples.control_rtts_ms == [20.0]  # what the supervisor's next step hears beside the MPC's


def test_a_core_without_tasks_flies_as_before() -> None:
    core = _core(())
    out = core.tick(TickInput(now_ns=0, fc=_fc(0), offboard=True))
    assert out.task_jobs.requests == ()
    assert "task_" not in " ".join(core.health())
