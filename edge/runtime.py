"""The one shape every edge service runs in: a core driven by one small runtime.

A service is a core (`EdgeCore`): its part you can drive on a fake clock (`handle` what arrived,
`tick` when time passes, say its `health`), plus what it declares on the bus at construction: its
subscriptions, which deliver into the runtime's inbox, its tokens and its publishers. Its effects are
what it publishes through the bus it is given (a `MemoryBus` in tests, which keeps every publication;
zenoh here), each publisher declared once with its priority. The runtime owns the rest, once:

- the zenoh session, opened as an edge client in a `with` and closed on the way out (`serve`);
- the one inbox: zenoh's threads decode and put into a bounded queue (never blocking: the oldest is
  dropped and counted), and a put into an empty inbox wakes the loop (unless the core is gathering
  its arrivals for a moment: `EdgeCore.gathering_s`, the MPC's batch window);
- one asyncio event loop per process: the core's `handle` with everything waiting, then its `tick`,
  again when the delay `tick` asked for has passed or something woke it (`wake`: a token changed);
- health (the log, /healthz and the health file), metrics, SIGTERM/SIGINT turned into the one stop
  signal, and the ready line.

Why asyncio and not threads: the QoS agent and the fleet planner talk HTTP to the operator on aiohttp
(and the agent serves its notification sink), which needs an event loop; on threads, those two would
run a loop beside the runtime's threads, both models in one process. The hand-off from a zenoh thread
costs about the same either way (measured here, 3000 hand-offs at 2 kHz: 17-26 us p50 through the
loop's `call_soon_threadsafe`, 15-19 us through a condition variable). Work too long for the loop (the
detector's search) runs on one thread the service starts with `Runtime.thread`; the MPC solves on the
loop: nothing else waits on it there (docs/benchmarks.md, `control_loop`, measured before and after).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dynqos.common.bus import Bus, Received
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.config import Config
from dynqos.common.lifecycle import ready_line, serving_metrics, stop_loop_on_signals, waker
from dynqos.common.metrics import ProcessMetrics
from dynqos.common.queues import BoundedQueue
from dynqos.edge.health import Health

log = logging.getLogger(__name__)

STOP_TASKS_S = 10.0  # after the stop signal, a service's tasks get this long to end (release, hand over)
INBOX_SIZE = 4096  # messages waiting for the core; beyond, the oldest is dropped and counted
IDLE_TICK_S = 0.5  # the longest a core waits for a tick when it asks for none sooner


@dataclass(frozen=True)
class Ports:
    """What a core is handed at construction: the bus it declares on and publishes to, the clock, and
    the inbox its subscriptions deliver into (the runtime's; in a test, one of its own)."""

    bus: Bus
    clock: Clock = field(default_factory=MonotonicClock)
    inbox: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(INBOX_SIZE))


class EdgeCore:
    """What a service is to the runtime. Every method runs on the runtime's one thread (the loop)."""

    name = "edge"
    health_interval_s = 5.0
    batch_s = 0.0  # > 0: arrivals are taken in one batch per tick, not as they come (the ROS 2 bridge)
    # Set by a tick: arrivals over the next `gathering_s` do not wake the loop, and the next turn takes
    # them together (the MPC's batch window, `[mpc] batch_window_s`). 0: every arrival wakes it.
    gathering_s = 0.0

    def handle(self, events: list[Received], now_ns: int) -> None:
        """Messages that arrived since the last call, oldest first."""

    def tick(self, now_ns: int) -> float:
        """Time passed (after every `handle`, and when asked for): timers, token changes; returns the
        seconds until the next tick is wanted (sooner if a message or a wake comes)."""
        return IDLE_TICK_S

    def health(self) -> str:
        return ""

    async def start(self, runtime: Runtime) -> None:
        """Before the ready line: what needs the loop (an HTTP client, a server, background tasks)."""

    async def finish(self) -> None:
        """After the stop signal, before the session closes: hand over, release, undeclare."""


class Runtime:
    def __init__(
        self,
        name: str,
        *,
        health: Health | None = None,
        clock: Clock | None = None,
        inbox_size: int = INBOX_SIZE,
    ) -> None:
        self.name = name
        self.clock = clock or MonotonicClock()
        self.health = health or Health(name)
        self.inbox: BoundedQueue[Received] = BoundedQueue(inbox_size)
        self.stopping = asyncio.Event()  # the one stop signal (bound to the loop at first use)
        self._stopped = False  # the same, for threads to read
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._gathering = False  # waiting with arrivals left in the inbox (`EdgeCore.gathering_s`)
        self._threads: list[threading.Thread] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._failure: BaseException | None = None

    @property
    def running(self) -> bool:
        """Until the stop signal: what a service's own thread loops on."""
        return not self._stopped

    def stop(self) -> None:
        """The stop signal, from the loop's thread (signals come there)."""
        self._stopped = True
        self.stopping.set()
        self._poke()

    def wake(self) -> None:
        """From any thread: tick the core soon (the fleet planner, once its plan is made). Before the
        loop runs, nothing: the first tick comes at once anyway."""
        if self._loop is not None:
            waker(self._loop, self._poke)()

    def _poke(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _arrived(self) -> None:
        """An arrival into the empty inbox: a turn now, unless the core is gathering its arrivals."""
        if not self._gathering:
            self._poke()

    def thread(self, target: Callable[[], Any], name: str) -> None:
        """Run `target` on its own thread, over and over until the stop signal (each call should return
        within a fraction of a second); joined before the session closes."""

        def loop() -> None:
            while self.running:
                target()

        worker = threading.Thread(target=loop, name=f"{self.name}-{name}", daemon=True)
        self._threads.append(worker)
        worker.start()

    def task(self, work: Coroutine[Any, Any, None]) -> None:
        """Run `work` on the loop beside the core. It should end soon after the stop signal (it gets
        STOP_TASKS_S, then is cancelled); if it fails, the service stops and the failure is raised."""
        task = asyncio.get_running_loop().create_task(work)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None and self._failure is None:
            self._failure = task.exception()
            self.stop()

    async def until(self, event: asyncio.Event) -> bool:
        """Wait for `event` or the stop signal; whether `event` came (False once stopping)."""
        if not event.is_set() and self.running:
            waits = {asyncio.ensure_future(event.wait()), asyncio.ensure_future(self.stopping.wait())}
            _, pending = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
            for waiting in pending:
                waiting.cancel()
        return event.is_set() and self.running

    async def drive(self, core: EdgeCore, ready: Callable[[], None] | None = None) -> None:
        """The service's life: handle and tick until the stop signal, from the first moment; it starts
        meanwhile and says ready once started."""
        loop = self._loop = asyncio.get_running_loop()
        stop_loop_on_signals(self.name, loop, self.stop)
        batched = core.batch_s > 0
        self.inbox.wake = None if batched else waker(loop, self._arrived)
        starting = loop.create_task(self._start(core, ready))
        self._tasks.add(starting)
        starting.add_done_callback(self._task_done)
        try:
            while self.running:
                events = self.inbox.drain()
                now = self.clock.now_ns()
                if events:
                    core.handle(events, now)
                delay = core.tick(now)
                self.health.maybe(core.health)
                gathering = core.gathering_s > 0
                if gathering:
                    delay = min(delay, core.gathering_s)
                await self._wait(min(delay, self.health.due_in()), batched or gathering)
        finally:
            self.inbox.wake = None
            self.stop()
            starting.cancel()  # a start still under way ends here (ready was never said)
            if self._tasks:
                _, late = await asyncio.wait(set(self._tasks), timeout=STOP_TASKS_S)
                for task in late:
                    task.cancel()
            await core.finish()
            for worker in self._threads:
                worker.join(timeout=5)
            log.info("%s: stopped; %s", self.name, core.health())
        if self._failure is not None:
            raise self._failure

    async def _start(self, core: EdgeCore, ready: Callable[[], None] | None) -> None:
        """The core's start, while it already handles what arrives (a QoS agent hears the drones before
        it takes over, to adopt their sessions); then the ready line."""
        await core.start(self)
        self.health.write("ready")
        if ready is not None:
            ready()
        self._poke()  # a tick now that it has started

    async def _wait(self, seconds: float, batched: bool) -> None:
        """Until a message (unless `batched`) or a wake comes, or `seconds` pass. One future and one
        timer per wait: a task per wait (asyncio.wait_for) costs more than the hand-off itself."""
        if seconds <= 0 or self._stopped or (self.inbox and not batched):
            return
        assert self._loop is not None
        waiter = self._waiter = self._loop.create_future()
        timer = self._loop.call_later(seconds, self._poke)
        self._gathering = batched
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None
            self._gathering = False


def serve(
    name: str,
    config: Config,
    make: Callable[[Config, Ports], EdgeCore],
    register: Callable[[Any, ProcessMetrics], None],
    *,
    health_file: Path | None = None,
    lease_s: float | None = None,
    inbox_size: int = INBOX_SIZE,
) -> int:
    """Run one edge service until SIGTERM: its metrics served, its zenoh session open as an edge client,
    its health file written, one ready line; everything closed on the way out."""
    from dynqos.common.transport import Role, open_bus  # here: `dynqos health` (a probe) needs no zenoh

    with serving_metrics(name, config) as metrics, open_bus(config.zenoh, Role.EDGE, lease_s=lease_s) as bus:
        runtime = Runtime(name, inbox_size=inbox_size)
        core = make(config, Ports(bus, runtime.clock, runtime.inbox))
        runtime.health = Health(name, core.health_interval_s, file=health_file, beat=metrics.health.beat)
        register(core, metrics)
        asyncio.run(runtime.drive(core, ready=lambda: ready_line(name)))
    return 0
