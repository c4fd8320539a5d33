"""The shell of the drone's offloaded tasks: each task's own code on its own thread (docs/offload.md).

The core (onboard/tasks.py) decides when to call, what counts and when the fallback flies; this shell
only carries it out. Each task gets one thread, fed the core's jobs through a small bounded queue, so
the user's `request`, `apply` and `fallback` never run on the control loop: whatever they do, the
setpoints keep their rate. What they do wrong is counted and said once per task and kind:

- raises, or builds a request the task's codec refuses: nothing is sent (the core counts it skipped);
- returns something that is not a Steer: the flight is left as it is;
- hangs: its jobs pile up and are dropped (the queue is bounded), its last Steer goes stale and the
  core stops applying it; the tick says so once.

A request goes out on every path, on the flow its class rides now (the core names it per job); answers
arrive on each path into the path's inbox, and the core takes the first in time.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher
from dynqos.common.clock import Clock
from dynqos.common.geometry import yaw_of
from dynqos.common.messages import TaskAnswer, TaskRequest
from dynqos.common.modes import Flow
from dynqos.common.queues import BoundedQueue
from dynqos.common.tasks import Codec, Drone, Onboard, PayloadError, Steer, TaskError, load
from dynqos.onboard.fc import FcState
from dynqos.onboard.links import PathLink
from dynqos.onboard.tasks import TaskJobs, TaskSent, TaskSteer

log = logging.getLogger(__name__)

JOBS_WAITING = 4  # jobs a task's thread may have waiting; beyond, the oldest is dropped (a hung task)
STUCK_S = 1.0  # a call of the user's onboard code running this long is said, once
# (default flow, priority flow, may be dropped): a control task's calls as the State, a bulk task's as
# the camera's frames (onboard/daemon.py, STREAMS)
PRIORITIES = {
    "control": (Priority.DATA_HIGH, Priority.REAL_TIME, False),
    "bulk": (Priority.DATA, Priority.INTERACTIVE_LOW, True),
}


@dataclass(frozen=True, slots=True)
class _Job:
    kind: str  # request | apply | fallback
    drone: Drone
    seq: int = 0
    flow: Flow = Flow.DEFAULT
    answer: TaskAnswer | None = None


def load_tasks(targets: Sequence[str]) -> list[Onboard[Any, Any]]:
    """[onboard] tasks, each "MODULE:ATTR" naming an Onboard; TaskError (one line) on any that fails,
    or on two tasks of one name."""
    onboards: list[Onboard[Any, Any]] = [load(target, Onboard) for target in targets]
    names = [o.task.name for o in onboards]
    if len(set(names)) != len(names):
        raise TaskError(f"[onboard] tasks: two tasks are named alike ({', '.join(sorted(names))})")
    return onboards


class TaskThread:
    """One task's onboard side: its thread, its publishers on each path, its counts."""

    def __init__(self, uav: str, onboard: Onboard[Any, Any], clock: Clock, stop: threading.Event) -> None:
        self.uav = uav
        self.onboard = onboard
        self.task = onboard.task
        self.codec: Codec[Any, Any] = Codec(self.task)
        self.clock = clock
        self.stop = stop
        self.jobs: BoundedQueue[_Job] = BoundedQueue(JOBS_WAITING)
        self.sent: BoundedQueue[TaskSent] = BoundedQueue(64)
        self.steers: BoundedQueue[TaskSteer] = BoundedQueue(16)
        self.publishers: list[tuple[Publisher, Publisher]] = []  # (default, priority) per path
        self.failures: dict[str, int] = {}
        self.busy_since_ns: int | None = None
        self._said: set[str] = set()
        self._thread = threading.Thread(target=self._run, name=f"task-{self.task.name}", daemon=True)

    def open(self, path: PathLink) -> None:
        on_default, on_priority, drop = PRIORITIES[self.task.flow]
        self.publishers.append(
            tuple(  # type: ignore[arg-type]
                path.bus.publisher(
                    keys.task_uplink(self.uav, flow, self.task.name),
                    priority,
                    drop_when_congested=drop,
                    express=flow is Flow.PRIORITY and not drop,
                )
                for flow, priority in ((Flow.DEFAULT, on_default), (Flow.PRIORITY, on_priority))
            )
        )
        key = keys.task_downlink(self.uav, self.task.name)
        path.bus.subscribe(key, path.inbox.tasks, expect=(TaskAnswer,))

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout_s: float) -> None:
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def stuck(self, now_ns: int) -> bool:
        since = self.busy_since_ns
        return since is not None and now_ns - since > STUCK_S * 1e9

    def _run(self) -> None:
        while not self.stop.is_set():
            job = self.jobs.get(timeout_s=0.1)
            if job is not None:
                self.busy_since_ns = self.clock.now_ns()
                try:
                    self._do(job)
                finally:
                    self.busy_since_ns = None

    def _do(self, job: _Job) -> None:
        if job.kind == "request":
            self._request(job)
        elif job.kind == "apply" and job.answer is not None:
            try:
                answer = self.codec.decode_answer(job.answer.body)
            except PayloadError as exc:
                self.fail("bad_answer", f"the edge's answer {job.answer.seq}: {exc}")
                return
            self._steer(lambda: self.onboard.apply(answer, job.drone), "apply")
        elif job.kind == "fallback":
            self._steer(lambda: self.onboard.fallback(job.drone), "fallback")

    def _request(self, job: _Job) -> None:
        body = None
        try:
            call = self.onboard.request(job.drone)
            if call is not None:
                body = self.codec.encode_request(call)
        except PayloadError as exc:
            self.fail("bad_request", str(exc))
        except Exception as exc:  # the user's code: it stays in its task
            self.fail("request_raised", f"{type(exc).__name__}: {exc}")
        if body is None:
            self.sent.put(TaskSent(self.task.name, job.seq, None))
            return
        now = self.clock.now_ns()
        message = TaskRequest(
            uav=self.uav,
            seq=job.seq,
            task=self.task.name,
            stamp_ns=now,
            budget_ms=self.task.deadline_s * 1000,
            body=body,
        )
        self.sent.put(TaskSent(self.task.name, job.seq, now))
        for default, priority in self.publishers:
            (priority if job.flow is Flow.PRIORITY else default).put(message)

    def _steer(self, call: Callable[[], Steer | None], what: str) -> None:
        try:
            steer = call()
        except Exception as exc:
            self.fail(f"{what}_raised", f"{type(exc).__name__}: {exc}")
            return
        if steer is None:
            return
        if not isinstance(steer, Steer):
            self.fail(f"{what}_not_steer", f"returned a {type(steer).__name__}, not a Steer")
            return
        self.steers.put(TaskSteer(self.task.name, steer, self.clock.now_ns()))

    def fail(self, kind: str, detail: str) -> None:
        self.failures[kind] = self.failures.get(kind, 0) + 1
        if kind not in self._said:
            self._said.add(kind)
            log.warning("task %s: %s: %s (counted; said once)", self.task.name, kind, detail)


class TaskRunner:
    """Every task of one drone: the jobs of each tick handed out, the threads' reports gathered."""

    def __init__(self, uav: str, onboards: Sequence[Onboard[Any, Any]], clock: Clock, stop: threading.Event):
        self.clock = clock
        self.threads = {o.task.name: TaskThread(uav, o, clock, stop) for o in onboards}
        self.uav = uav

    @property
    def tasks(self) -> tuple[Any, ...]:
        return tuple(t.task for t in self.threads.values())

    def open(self, path: PathLink) -> None:
        for thread in self.threads.values():
            thread.open(path)

    def start(self) -> None:
        for thread in self.threads.values():
            thread.start()

    def join(self, timeout_s: float) -> None:
        for thread in self.threads.values():
            thread.join(timeout_s)

    def reports(self) -> tuple[list[TaskSent], list[TaskSteer]]:
        sent = [s for t in self.threads.values() for s in t.sent.drain()]
        return sent, [s for t in self.threads.values() for s in t.steers.drain()]

    def hand_out(self, jobs: TaskJobs, fc: FcState | None, flying: bool) -> None:
        """The core's jobs onto the tasks' threads, each with the drone as it is now."""
        if not (jobs.requests or jobs.apply or jobs.fallback) or fc is None:
            return
        now = self.clock.now_ns()
        drone = Drone(self.uav, now / 1e9, fc.pos_m, fc.vel_mps, yaw_of(fc.quat), flying)
        for name in jobs.fallback:
            self._give(name, _Job("fallback", drone), now)
        for answer in jobs.apply:
            self._give(answer.task, _Job("apply", drone, answer=answer), now)
        for name, seq, flow in jobs.requests:
            self._give(name, _Job("request", drone, seq, flow), now)

    def _give(self, name: str, job: _Job, now_ns: int) -> None:
        thread = self.threads[name]
        thread.jobs.put(job)
        if thread.stuck(now_ns):
            thread.fail("stuck", f"its onboard code has not returned for over {STUCK_S:g} s")

    def health(self) -> dict[str, object]:
        out: dict[str, object] = {}
        for name, thread in self.threads.items():
            failures = sum(thread.failures.values())
            if failures or thread.jobs.dropped:
                out[f"task_{name}_failures"] = f"{failures},dropped_jobs={thread.jobs.dropped}"
        return out
