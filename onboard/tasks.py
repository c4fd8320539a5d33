"""The drone's side of its offloaded tasks as pure logic: when to call, whether an answer counts, when
to fly the fallback (docs/offload.md).

Each task has a `TaskTimer` on the drone's clock. A request is due every period while the drone flies
offboard (a bulk task's period stretches with the camera's rate factor: it is throttled with the
camera). The deadline is enforced here, by the tick, not by waiting for the answer: a request still
unanswered `deadline` after it was sent is a miss, and a miss sends the task to its fallback at once.
An answer applies only if it is for the latest request sent and arrived within the deadline; one for an
older request is stale, one past the deadline late, and neither is applied.

Back from the fallback: one answer in time does it after a lone miss; after OPEN_AFTER misses in a row
the circuit is open, and it takes RECOVER_AFTER answers in time in a row (each period's request is the
probe), so a flapping link does not flap the task.

`OnboardTasks` holds every task's timer and tells the shell, each tick, what to run on the tasks' own
threads (onboard/task_runner.py): the requests to build and send, the answers to apply, the fallbacks
to fly. A control task's round trips and oldest unanswered request feed the supervisor like the MPC's,
a bulk task's like the camera's.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

from dynqos.common.messages import TaskAnswer
from dynqos.common.modes import Flow
from dynqos.common.tasks import Steer, Task

OPEN_AFTER = 3  # misses in a row that open the circuit
RECOVER_AFTER = 3  # answers in time in a row that close it again
MAX_OUTSTANDING = 16  # requests remembered while unanswered; older ones are misses already
MAX_SAMPLES = 256  # round trips kept for the supervisor between its steps


class Mode(str, enum.Enum):
    EDGE = "edge"  # the latest answer in time is applied
    FALLBACK = "fallback"  # the task's onboard fallback flies


class Verdict(str, enum.Enum):
    APPLY = "apply"
    RECOVERING = "recovering"  # in time, but the circuit wants more before the edge flies again
    STALE = "stale"  # for an older request than the latest sent
    LATE = "late"  # past the deadline
    UNKNOWN = "unknown"  # for no request this drone remembers (a replayed or foreign answer)


@dataclass
class TaskCounts:
    requests: int = 0
    skipped: int = 0  # the request builder returned None, raised, or built junk: nothing sent
    answers: int = 0
    applied: int = 0
    stale: int = 0
    late: int = 0
    unknown: int = 0
    misses: int = 0
    fallbacks: int = 0  # switches to the fallback
    fallback_ns: int = 0  # time flown on the fallback


class TaskTimer:
    def __init__(self, task: Task[object, object], start_ns: int) -> None:
        self.task = task
        self.mode = Mode.EDGE
        self.counts = TaskCounts()
        self.outstanding: dict[int, int] = {}  # seq -> sent_ns, in sending order
        self.missed: dict[int, int] = {}  # the same, past their deadline: a late answer is still timed
        self.latest_seq = 0
        self._seq = 0
        self._next_due_ns = start_ns
        self._misses_in_row = 0
        self._in_time_in_row = 0
        self._mode_since_ns = start_ns
        self.rtts_ms: list[float] = []  # for the supervisor's next step
        self.status_rtts_ms: list[float] = []  # for the next status

    def due(self, now_ns: int, rate_factor: float = 1.0) -> int | None:
        """The seq of a request to send now, or None. A bulk task's period stretches by 1/rate_factor."""
        if now_ns < self._next_due_ns:
            return None
        stretch = 1.0 if self.task.flow == "control" else 1.0 / max(rate_factor, 0.05)
        period = round(self.task.period_ns * stretch)
        self._next_due_ns = max(self._next_due_ns + period, now_ns - period // 2)
        self._seq += 1
        return self._seq

    def sent(self, seq: int, sent_ns: int | None) -> None:
        """The shell sent request `seq` at `sent_ns` (None: skipped, nothing went out)."""
        if sent_ns is None:
            self.counts.skipped += 1
            return
        self.counts.requests += 1
        self.outstanding[seq] = sent_ns
        self.latest_seq = max(self.latest_seq, seq)
        while len(self.outstanding) > MAX_OUTSTANDING:
            del self.outstanding[next(iter(self.outstanding))]

    def answered(self, seq: int, arrival_ns: int) -> Verdict:
        """What an answer counts for. Every answer to a request still remembered is timed, a late one too:
        the supervisor must see how late the calls come, not only the ones in time."""
        sent_ns = self.outstanding.pop(seq, None)
        if sent_ns is None:
            sent_ns = self.missed.pop(seq, None)
        if sent_ns is None:
            self.counts.unknown += 1
            return Verdict.UNKNOWN
        self.counts.answers += 1
        rtt_ns = arrival_ns - sent_ns
        for samples in (self.rtts_ms, self.status_rtts_ms):
            samples.append(rtt_ns / 1e6)
            del samples[:-MAX_SAMPLES]
        if rtt_ns > self.task.deadline_ns:
            self.counts.late += 1
            return Verdict.LATE  # its miss was counted when the deadline passed
        if seq != self.latest_seq:
            self.counts.stale += 1
            return Verdict.STALE
        self._in_time_in_row += 1
        if self.mode is Mode.FALLBACK:
            needed = RECOVER_AFTER if self._misses_in_row >= OPEN_AFTER else 1
            if self._in_time_in_row < needed:
                return Verdict.RECOVERING
            self._switch(Mode.EDGE, arrival_ns)
        self._misses_in_row = 0
        self.counts.applied += 1
        return Verdict.APPLY

    def expire(self, now_ns: int) -> bool:
        """Requests past their deadline become misses; True if this sent the task to its fallback."""
        late = [seq for seq, sent in self.outstanding.items() if now_ns - sent > self.task.deadline_ns]
        for seq in late:
            self.missed[seq] = self.outstanding.pop(seq)
            self.counts.misses += 1
            self._misses_in_row += 1
            self._in_time_in_row = 0
        while len(self.missed) > MAX_OUTSTANDING:
            del self.missed[next(iter(self.missed))]
        if late and self.mode is Mode.EDGE:
            self._switch(Mode.FALLBACK, now_ns)
            self.counts.fallbacks += 1
            return True
        return False

    def oldest_outstanding_ms(self, now_ns: int) -> float | None:
        if not self.outstanding:
            return None
        return (now_ns - next(iter(self.outstanding.values()))) / 1e6

    def take_rtts(self) -> list[float]:
        taken, self.rtts_ms = self.rtts_ms, []
        return taken

    def fallback_s(self, now_ns: int) -> float:
        ongoing = now_ns - self._mode_since_ns if self.mode is Mode.FALLBACK else 0
        return (self.counts.fallback_ns + ongoing) / 1e9

    def _switch(self, mode: Mode, now_ns: int) -> None:
        if self.mode is Mode.FALLBACK:
            self.counts.fallback_ns += now_ns - self._mode_since_ns
        self.mode, self._mode_since_ns = mode, now_ns


@dataclass(frozen=True, slots=True)
class TaskSent:
    """The shell's report of a request: sent at `sent_ns`, or skipped (None)."""

    task: str
    seq: int
    sent_ns: int | None


@dataclass(frozen=True, slots=True)
class TaskSteer:
    """What a task's onboard side made of the flight, and when: the shell's latest result per task."""

    task: str
    steer: Steer
    made_ns: int


@dataclass(frozen=True, slots=True)
class TaskJobs:
    """What the shell runs on the tasks' threads after this tick."""

    requests: tuple[tuple[str, int, Flow], ...] = ()  # (task, seq, flow): build and send on that flow
    apply: tuple[TaskAnswer, ...] = ()  # answers in time for the latest request
    fallback: tuple[str, ...] = ()  # tasks whose fallback flies this period


@dataclass
class TaskSamples:
    """What the tasks add to the supervisor's evidence at a step."""

    control_rtts_ms: list[float] = field(default_factory=list)
    bulk_rtts_ms: list[float] = field(default_factory=list)
    control_outstanding_ms: float | None = None
    bulk_outstanding_ms: float | None = None


class OnboardTasks:
    def __init__(self, tasks: Sequence[Task[object, object]], start_ns: int) -> None:
        self.timers = {task.name: TaskTimer(task, start_ns) for task in tasks}
        self._steers: dict[str, TaskSteer] = {}

    def tick(
        self,
        now_ns: int,
        flying: bool,
        answers: Sequence[tuple[TaskAnswer, int]],
        sent: Sequence[TaskSent],
        flows: dict[str, Flow],
        rate_factor: float,
    ) -> tuple[TaskJobs, list[tuple[int, str]]]:
        """One control tick: the shell's reports in, the jobs out, and what to log. `flows`: the flow of
        each class now (control: the State's, bulk: the camera's)."""
        events: list[tuple[int, str]] = []  # (a logging level, the line)
        for report in sent:
            if (timer := self.timers.get(report.task)) is not None:
                timer.sent(report.seq, report.sent_ns)
        apply = []
        for answer, arrival_ns in answers:
            timer = self.timers.get(answer.task)
            if timer is None:
                continue
            was = timer.mode
            if timer.answered(answer.seq, arrival_ns) is Verdict.APPLY:
                apply.append(answer)
                if was is Mode.FALLBACK:
                    said = f"task {answer.task}: answers in time again: the edge's answer applies"
                    events.append((logging.INFO, said))
        requests, fallback = [], []
        for name, timer in self.timers.items():
            missed = timer.expire(now_ns)
            if missed:
                said = f"task {name}: no answer within {timer.task.deadline_s * 1000:g} ms: fallback"
                events.append((logging.WARNING, said))
            if not flying:
                continue
            seq = timer.due(now_ns, rate_factor)
            if seq is not None:
                requests.append((name, seq, flows[timer.task.flow]))
            if timer.mode is Mode.FALLBACK and (missed or seq is not None):
                fallback.append(name)  # at the miss, then once a period
        return TaskJobs(tuple(requests), tuple(apply), tuple(fallback)), events

    def take_samples(self, now_ns: int) -> TaskSamples:
        samples = TaskSamples()
        for timer in self.timers.values():
            control = timer.task.flow == "control"
            (samples.control_rtts_ms if control else samples.bulk_rtts_ms).extend(timer.take_rtts())
            oldest = timer.oldest_outstanding_ms(now_ns)
            if control:
                samples.control_outstanding_ms = _max(samples.control_outstanding_ms, oldest)
            else:
                samples.bulk_outstanding_ms = _max(samples.bulk_outstanding_ms, oldest)
        return samples

    def steer(self, steers: Sequence[TaskSteer], now_ns: int) -> float | None:
        """The heading the tasks want now: the newest fresh Steer with a yaw (a steer older than two
        periods and a deadline is dropped: its task's thread has stopped answering)."""
        for made in steers:
            self._steers[made.task] = made
        best: TaskSteer | None = None
        for name, made in self._steers.items():
            timer = self.timers.get(name)
            if timer is None or made.steer.yaw_rad is None:
                continue
            if now_ns - made.made_ns > 2 * timer.task.period_ns + timer.task.deadline_ns:
                continue
            if best is None or made.made_ns > best.made_ns:
                best = made
        return None if best is None else best.steer.yaw_rad

    def status(self, now_ns: int) -> tuple[tuple[str, str, int, int, int, float, tuple[float, ...]], ...]:
        """Each task as SupervisorStatus.tasks carries it; its round trips since the last status."""
        out = []
        for name, timer in self.timers.items():
            c = timer.counts
            rtts, timer.status_rtts_ms = tuple(timer.status_rtts_ms), []
            out.append(
                (name, timer.mode.value, c.requests, c.applied, c.misses, timer.fallback_s(now_ns), rtts)
            )
        return tuple(out)

    def health(self, now_ns: int) -> dict[str, object]:
        out: dict[str, object] = {}
        for name, timer in self.timers.items():
            c = timer.counts
            out[f"task_{name}"] = (
                f"{timer.mode.value}:{c.applied}/{c.requests}"
                f",miss={c.misses},late={c.late},stale={c.stale},skipped={c.skipped}"
                f",fallback_s={timer.fallback_s(now_ns):.1f}"
            )
        return out


def _max(a: float | None, b: float | None) -> float | None:
    if a is None:
        return b
    return a if b is None else max(a, b)
