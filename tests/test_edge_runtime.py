"""The edge runtime (edge/runtime.py) around a small core: what arrives from another thread wakes it
and is handled in order, ticks come when asked, a batched core takes its arrivals per tick, and the
one stop signal ends the tasks, the threads and the core in that order; a failing task stops it."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import pytest

from dynqos.common.bus import Received
from dynqos.common.errors import DynqosError
from dynqos.common.messages import State
from dynqos.edge.health import Health, check_health
from dynqos.edge.runtime import EdgeCore, Runtime

pytestmark = pytest.mark.timeout(30)


def _state(seq: int) -> Received:
    message = State(uav="uav1", seq=seq, stamp_ns=0, pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                    quat=(1.0, 0.0, 0.0, 0.0))  # fmt: skip
    return Received("dynqos/uav1/up/d/state", message, 0)


class Recorder(EdgeCore):
    """Stops the runtime once it has seen `until` messages; records what it was called with."""

    name = "recorder"

    def __init__(self, until: int, tick_s: float = 10.0) -> None:
        self.until = until
        self.tick_s = tick_s
        self.seen: list[int] = []
        self.batches = 0
        self.ticks = 0
        self.order: list[str] = []
        self.runtime: Runtime | None = None

    async def start(self, runtime: Runtime) -> None:
        self.runtime = runtime
        self.order.append("start")

    def handle(self, events: list[Received], now_ns: int) -> None:
        self.batches += 1
        self.seen += [e.message.seq for e in events]

    def tick(self, now_ns: int) -> float:
        self.ticks += 1
        if len(self.seen) >= self.until and self.order:  # once started
            assert self.runtime is not None
            self.runtime.stop()
        return self.tick_s

    def health(self) -> str:
        return f"seen={len(self.seen)}"

    async def finish(self) -> None:
        self.order.append("finish")


def _feed(runtime: Runtime, count: int, started: threading.Event) -> threading.Thread:
    """A zenoh-like thread: puts `count` states into the inbox once the core has started."""

    def put() -> None:
        started.wait(10)
        for seq in range(count):
            runtime.inbox.put(_state(seq))

    thread = threading.Thread(target=put, daemon=True)
    thread.start()
    return thread


def test_messages_from_another_thread_wake_the_core_and_arrive_in_order(tmp_path: Path) -> None:
    """The core asks for a tick only every 10 s, so only the inbox's wake can bring the messages in."""
    runtime = Runtime("recorder", health=Health("recorder", file=tmp_path / "health"))
    core = Recorder(until=500)
    started = threading.Event()
    feeder = _feed(runtime, 500, started)
    ready: list[bool] = []

    def say_ready() -> None:
        ready.append(True)
        started.set()

    asyncio.run(runtime.drive(core, ready=say_ready))
    feeder.join(5)
    assert core.seen == list(range(500))
    assert ready == [True]
    assert core.order == ["start", "finish"]
    assert 1 <= core.batches <= 500
    assert check_health(tmp_path / "health", max_age_s=60) == "recorder: ready"
    assert not runtime.running


def test_a_batched_core_takes_its_arrivals_at_its_ticks_only() -> None:
    runtime = Runtime("batched")
    core = Recorder(until=50, tick_s=0.05)
    core.batch_s = 0.05
    for seq in range(50):  # all waiting before the first turn
        runtime.inbox.put(_state(seq))
    asyncio.run(runtime.drive(core))
    assert core.seen == list(range(50))
    assert core.batches == 1


def test_a_gathering_core_takes_what_arrives_in_its_window_in_one_turn() -> None:
    """The MPC's batch window: after its first State, the core asks to gather for 0.5 s; the 49 States
    put meanwhile (from another thread, each a wake when the inbox was empty) wake nothing, and all
    come in the next turn."""
    runtime = Runtime("gathering")
    first = threading.Event()

    class Gathering(Recorder):
        def handle(self, events: list[Received], now_ns: int) -> None:
            super().handle(events, now_ns)
            first.set()

        def tick(self, now_ns: int) -> float:
            self.gathering_s = 0.5 if len(self.seen) == 1 else 0.0
            return super().tick(now_ns)

    core = Gathering(until=50)

    def rest() -> None:
        first.wait(10)
        for seq in range(1, 50):
            runtime.inbox.put(_state(seq))

    feeder = threading.Thread(target=rest, daemon=True)
    feeder.start()
    runtime.inbox.put(_state(0))
    asyncio.run(runtime.drive(core))
    feeder.join(5)
    assert core.seen == list(range(50))
    assert core.batches == 2


def test_a_thread_of_the_service_runs_until_the_stop_signal_and_is_joined() -> None:
    runtime = Runtime("threaded")
    calls: list[int] = []

    def work() -> None:
        calls.append(1)
        threading.Event().wait(0.001)

    class WithThread(Recorder):
        async def start(self, rt: Runtime) -> None:
            await super().start(rt)
            rt.thread(work, "work")

    core = WithThread(until=1, tick_s=0.01)
    runtime.inbox.put(_state(0))
    asyncio.run(runtime.drive(core))
    assert calls
    count = len(calls)
    threading.Event().wait(0.05)  # the thread was joined: no call after the drive ended
    assert len(calls) == count


def test_a_failing_task_stops_the_service_and_its_failure_is_raised() -> None:
    runtime = Runtime("failing")

    class Failing(Recorder):
        async def start(self, rt: Runtime) -> None:
            await super().start(rt)

            async def fail() -> None:
                raise DynqosError("the operator refused the plan")

            rt.task(fail())

    core = Failing(until=10**9)
    with pytest.raises(DynqosError, match="refused the plan"):
        asyncio.run(runtime.drive(core))
    assert core.order == ["start", "finish"]


def test_a_task_that_waits_for_an_event_ends_at_the_stop_signal() -> None:
    runtime = Runtime("waiting")
    outcome: list[bool] = []

    class Waiting(Recorder):
        async def start(self, rt: Runtime) -> None:
            await super().start(rt)
            never = asyncio.Event()

            async def wait() -> None:
                outcome.append(await rt.until(never))

            rt.task(wait())

    core = Waiting(until=1)
    runtime.inbox.put(_state(0))
    asyncio.run(runtime.drive(core))
    assert outcome == [False]


def test_a_core_handles_what_arrives_while_it_starts() -> None:
    """The QoS agent hears the drones while it settles, so that it can adopt their sessions when it
    takes over: a start that waits for a message ends only if messages are handled meanwhile."""
    runtime = Runtime("settling")
    ready: list[int] = []

    class Settling(Recorder):
        def __init__(self) -> None:
            super().__init__(until=1)
            self.heard = asyncio.Event()

        async def start(self, rt: Runtime) -> None:
            self.runtime = rt
            await self.heard.wait()
            self.order.append("start")

        def handle(self, events: list[Received], now_ns: int) -> None:
            super().handle(events, now_ns)
            self.heard.set()

    core = Settling()
    runtime.inbox.put(_state(0))
    asyncio.run(runtime.drive(core, ready=lambda: ready.append(len(core.seen))))
    assert ready == [1]  # ready once started, having handled the message
    assert core.order == ["start", "finish"]
