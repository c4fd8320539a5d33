"""`dynqos edge serve MODULE:ATTR`: a user's task served with what every edge service has.

The user's `handle` (common/tasks.py, `Edge`) runs on a worker thread, never on the runtime's loop, so
nothing it does stops the process's other work: the loop keeps taking requests, saying health and
serving metrics. Each request waits in one slot per drone (a newer one replaces it: an answer to an old
request is of no use to the drone) and is dropped unread once it has waited past its budget. Whatever
the handler does wrong is counted by kind and said in one log line naming the task, the first time:

- raises: no answer; the drone flies its fallback;
- returns junk (not the task's answer type, or over its size bound): no answer;
- is slow (the answer would reach the drone past its budget): not sent, counted `late`;
- hangs (no return within HANG_FACTOR budgets, at least HANG_MIN_S): the worker is left behind and a
  new one serves; after MAX_ABANDONED such workers the service stops serving and its health says so.

Replicas share the drones as the detector's do (edge/membership.py, `LiveSet`): a drone's requests are
served by the first-ranked live replica, and by the next as soon as that one's token goes.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher, Received
from dynqos.common.config import Config
from dynqos.common.messages import TaskAnswer, TaskRequest
from dynqos.common.metrics import ProcessMetrics
from dynqos.common.tasks import Codec, Edge, PayloadError, Service, Task
from dynqos.edge import metrics
from dynqos.edge.membership import LiveSet, default_replica_id
from dynqos.edge.runtime import EdgeCore, Ports, Runtime, serve

log = logging.getLogger(__name__)

HANG_FACTOR = 10.0  # a call that has not returned after this many budgets is hung
HANG_MIN_S = 1.0
MAX_ABANDONED = 4  # hung workers left behind before the service gives up serving
WAIT_S = 0.1  # a worker's longest wait for a request (it checks the stop signal between)
FAILURES = ("raised", "bad_answers", "late", "hung", "bad_requests")


@dataclass
class _Worker:
    """One worker thread's call in progress (`busy_since_ns` None between calls)."""

    number: int
    busy_since_ns: int | None = None
    call: str = ""  # the drone and request in progress, for the hang's log line
    abandoned: bool = False
    thread: threading.Thread | None = field(default=None, repr=False)


class TaskService(EdgeCore):
    def __init__(self, edge: Edge[Any, Any], config: Config, ports: Ports, *, replica: str = "") -> None:
        task = edge.task
        self.edge = edge
        self.task = task
        self.name = service_name(task.name)
        self.codec: Codec[Any, Any] = Codec(task)
        self.bus = ports.bus
        self.clock = ports.clock
        self.inbox = ports.inbox
        self.stats = self.bus.subscribe(
            keys.task_uplink_all_drones(task.name), self.inbox, expect=(TaskRequest,)
        )
        self.replicas = LiveSet(self.name, replica or default_replica_id(), self.bus)
        self.hang_ns = round(max(HANG_MIN_S, HANG_FACTOR * task.deadline_s) * 1e9)
        self.counters = dict.fromkeys(
            ("requests", "answers", "superseded", "expired", "others", *FAILURES), 0
        )
        self.handle_ms: list[float] = []  # the last calls' times, for the health line's median
        self._pending: dict[str, Received] = {}  # the newest request of each drone, not yet taken
        self._ready = threading.Condition()
        self._publishers: dict[str, Publisher] = {}
        self._said: set[str] = set()
        self._workers: list[_Worker] = []
        self._abandoned = 0
        self._running = True

    # ---- the loop's side ------------------------------------------------------------------------------

    def handle(self, events: list[Received], now_ns: int) -> None:
        """Each request into its drone's slot; one already there was not served in time for this one."""
        self.replicas.apply()
        with self._ready:
            for item in events:
                request = item.message
                if not isinstance(request, TaskRequest):
                    continue
                if request.task != self.task.name:
                    self._count("bad_requests", f"a request names task {request.task!r}")
                    continue
                if not self.replicas.serves(request.uav):
                    self.counters["others"] += 1
                    continue
                self.counters["requests"] += 1
                if request.uav in self._pending:
                    self.counters["superseded"] += 1
                self._pending[request.uav] = item
            self._ready.notify()

    def tick(self, now_ns: int) -> float:
        """A call running past the hang bound leaves its worker behind, and a new one serves."""
        self.replicas.apply()
        for worker in list(self._workers):
            since = worker.busy_since_ns
            if since is None or worker.abandoned or now_ns - since < self.hang_ns:
                continue
            worker.abandoned = True
            self._workers.remove(worker)
            self._abandoned += 1
            self._count("hung", f"{worker.call} has not returned after {(now_ns - since) / 1e9:.1f} s")
            if self._abandoned >= MAX_ABANDONED:
                log.error("%s: %d calls hung: serving no more requests", self.name, self._abandoned)
            else:
                self._start_worker()
        return 0.1

    def health(self) -> str:
        ms = sorted(self.handle_ms) or [0.0]
        counts = " ".join(f"{k}={v}" for k, v in self.counters.items())
        serving = "no (hung)" if self._abandoned >= MAX_ABANDONED else "yes"
        replicas = f"replica={self.replicas.me} replicas={len(self.replicas.members)}"
        rejected = self.stats.rejected
        return (
            f"{counts} rejected={rejected} handle_ms_p50={ms[len(ms) // 2]:.2f} serving={serving} {replicas}"
        )

    async def start(self, runtime: Runtime) -> None:
        self._start_worker()

    async def finish(self) -> None:
        self._running = False
        with self._ready:
            self._ready.notify_all()
        for worker in self._workers:
            if worker.thread is not None:
                worker.thread.join(timeout=2 * WAIT_S + self.task.deadline_s)
        self.replicas.close()

    # ---- the workers' side ----------------------------------------------------------------------------

    def _start_worker(self) -> None:
        worker = _Worker(len(self._workers) + self._abandoned + 1)
        worker.thread = threading.Thread(
            target=self._work, args=(worker,), name=f"{self.name}-{worker.number}", daemon=True
        )
        self._workers.append(worker)
        worker.thread.start()

    def _work(self, worker: _Worker) -> None:
        while self._running and not worker.abandoned:
            item = self.next_request()
            if item is not None:
                self.serve_one(item, worker)

    def next_request(self) -> Received | None:
        """The request that has waited longest, or None after WAIT_S (a worker's, or a test's, take)."""
        with self._ready:
            if not self._pending and not self._ready.wait(WAIT_S):
                return None
            if not self._pending:
                return None
            uav = min(self._pending, key=lambda u: self._pending[u].arrival_ns)
            return self._pending.pop(uav)

    def serve_one(self, item: Received, worker: _Worker) -> None:
        """One call: checked in, the user's handler, checked out, answered if still of use."""
        request = item.message
        assert isinstance(request, TaskRequest)
        waited_ms = (self.clock.now_ns() - item.arrival_ns) / 1e6
        if waited_ms > request.budget_ms:
            self.counters["expired"] += 1
            return
        try:
            call = self.codec.decode_request(request.body)
        except PayloadError as exc:
            self._count("bad_requests", f"{request.uav} request {request.seq}: {exc}")
            return
        worker.call = f"the call for {request.uav} request {request.seq}"
        start = worker.busy_since_ns = self.clock.now_ns()
        try:
            answer = self.edge.handle(call)
        except BaseException as exc:  # the user's code: whatever it raises stays in its task
            self._count("raised", f"{request.uav} request {request.seq}: {type(exc).__name__}: {exc}")
            return
        finally:
            worker.busy_since_ns = None
        took_ms = (self.clock.now_ns() - start) / 1e6
        if worker.abandoned:
            return  # declared hung meanwhile: far past its budget
        self.handle_ms.append(took_ms)
        del self.handle_ms[:-500]
        self._answer(request, answer, waited_ms, took_ms)

    def _answer(self, request: TaskRequest, answer: Any, waited_ms: float, took_ms: float) -> None:
        try:
            body = self.codec.encode_answer(answer)
        except PayloadError as exc:
            self._count("bad_answers", f"{request.uav} request {request.seq}: {exc}")
            return
        if waited_ms + took_ms > request.budget_ms:
            why = f"waited {waited_ms:.1f} ms and took {took_ms:.1f} ms of a {request.budget_ms:g} ms budget"
            self._count("late", f"{request.uav} request {request.seq}: {why}")
            return
        message = TaskAnswer(
            uav=request.uav,
            seq=request.seq,
            task=self.task.name,
            stamp_ns=request.stamp_ns,
            handle_ms=took_ms,
            replica=self.replicas.me,
            body=body,
        )
        self._publisher(request.uav).put(message)
        self.counters["answers"] += 1

    def _publisher(self, uav: str) -> Publisher:
        pub = self._publishers.get(uav)
        if pub is None:
            control = self.task.flow == "control"
            priority = Priority.REAL_TIME if control else Priority.DATA_HIGH
            pub = self._publishers[uav] = self.bus.publisher(
                keys.task_downlink(uav, self.task.name), priority, express=control
            )
        return pub

    def _count(self, kind: str, detail: str) -> None:
        """A failure of the user's code or data: counted, and said once per kind (the health line and
        the metrics carry the counts from then on)."""
        self.counters[kind] += 1
        if kind not in self._said:
            self._said.add(kind)
            log.warning("%s: %s: %s (counted in %s=; said once)", self.name, kind, detail, kind)


def service_name(task: str) -> str:
    """The service's name in logs, health, metrics, replica tokens and its identity: task-<name>."""
    return f"task-{task}"


def run(
    declared: Edge[Any, Any] | Service[Any, Any],
    config: Config,
    *,
    health_file: Path | None = None,
    replica: str = "",
) -> int:
    """`dynqos edge serve` until SIGTERM (edge/runtime.py's `serve`): an `Edge`'s function on a
    TaskService, a `Service`'s own core (the MPC, the detector: `dynqos edge mpc` comes here too)."""
    if isinstance(declared, Service):
        name, task = declared.service_name, declared.task
        log.info("%s: serving task %s (%s)", name, task.name, _declared(task))

        def build(cfg: Config, ports: Ports) -> EdgeCore:
            core: EdgeCore = declared.make(cfg, ports, replica)
            return core

        register = declared.metrics or _no_metrics
        return serve(name, config, build, register, health_file=health_file)
    edge = declared

    def make(cfg: Config, ports: Ports) -> TaskService:
        return TaskService(edge, cfg, ports, replica=replica)

    return serve(service_name(edge.task.name), config, make, metrics.task, health_file=health_file)


def _declared(task: Task[Any, Any]) -> str:
    return f"{task.rate_hz:g} Hz, deadline {task.deadline_s * 1e3:g} ms, {task.flow} flow"


def _no_metrics(core: Any, process: ProcessMetrics) -> None:
    """A Service that registers nothing of its own: the process's metrics alone."""
