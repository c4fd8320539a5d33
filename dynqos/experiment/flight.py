"""What every flight shares, one drone or a fleet: the cell's control API, the recorder's streams, the
wait for offloading, the flight loop (load, faults, memory, the cell's counters) and stopping every
process whatever happens. dynqos/experiment/runner.py flies every scenario with them."""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
import urllib.request
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.clock import millis
from dynqos.common.config import ZenohConfig
from dynqos.common.errors import DynqosError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import OFFBOARD, Reference, State, SupervisorStatus
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Received, Role, endpoints, open_bus
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.machine import own_machine, read_cpu_times, usable_core_count
from dynqos.experiment.processes import Processes, resident_memory
from dynqos.plan.faults import FaultWindow
from dynqos.plan.flight import FlightPlan, Launch
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import UAV, Scenario

log = logging.getLogger(__name__)


def launch(
    procs: Processes, item: Launch, configs: Mapping[str, Path], stop_with: str | None = None
) -> dict[str, Any]:
    """Start one process of the plan: its config file from `configs` (its key: the run's, site B's or a
    drone's), niced where the plan says. Its ready line (inside `together`: {} now)."""
    program = ["nice", "-n", str(item.nice), procs.exe] if item.nice else None
    config = configs[item.config] if item.config else None
    return procs.start(
        item.name,
        list(item.args),
        timeout_s=item.timeout_s,
        program=program,
        config=config,
        stop_with=stop_with,
    )


def start_together(procs: Processes, items: tuple[Launch, ...], configs: Mapping[str, Path]) -> None:
    with procs.together():
        for item in items:
            launch(procs, item, configs)


def start_network(
    procs: Processes, plan: FlightPlan, configs: Mapping[str, Path]
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The routers and cells, at once (a cell connects to its router only when a drone connects to it);
    each cell's ready line, with its ports (None: no site B)."""
    start_together(procs, plan.network, configs)
    return procs.info["cell"], procs.info.get("cell-b")


RECORD_PERIOD_S = 0.1  # the recorder's sampling period
PROGRESS_EVERY_S = 10.0  # a progress log line this often when stderr is not a terminal
CELL_POLL_S = 0.5  # how often the cell's counters are read
MACHINE_SAMPLE_S = 1.0  # how often the machine's CPU times are read (one-second busy shares)
OFFLOAD_TIMEOUT_S = 60.0  # from the daemon's start to its first offboard state
QUEUE_ITEMS = 200_000  # per recorded stream: 30 min of states at 50 Hz, with room


def get_json(port: int, path: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        data: dict[str, Any] = json.loads(response.read())
        return data


def post_json(port: int, path: str, body: dict[str, Any]) -> dict[str, Any]:
    request = urllib.request.Request(
        f"http://127.0.0.1:{port}{path}",
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=5) as response:
        data: dict[str, Any] = json.loads(response.read())
        return data


def cell_event(port: int) -> Callable[[dict[str, Any]], object]:
    """A way to send an event (the load, a fault) to the cell whose control API is on `port`."""
    return lambda event: post_json(port, "/events", event)


def recorder_bus(zenoh: ZenohConfig, zenoh_b: ZenohConfig | None = None) -> Bus:
    """The recorder's session, an edge client: with two sites it connects to both routers (each message
    then comes twice: Streams keeps one), so it hears on when one site is killed."""
    connect = [endpoints(z, Role.EDGE)[0][0] for z in (zenoh, zenoh_b) if z is not None]
    return open_bus(zenoh, Role.EDGE, connect=connect)


def fly_and_stop(
    scenario: Scenario,
    folder: Path,
    procs: Processes,
    rec: Recording,
    fly: Callable[[], None],
    stop: threading.Event,
    progress: bool,
) -> tuple[bool, str]:
    """Run `fly` (start the rest and record the flight); whatever happens, read each process's CPU, stop
    them all in reverse order and read the QoD sessions the operator was left with. (ok, failure)."""
    ok, failure = True, ""
    try:
        fly()
        if stop.is_set():
            ok, failure = False, "interrupted"
    except DynqosError as exc:
        ok, failure = False, str(exc)
        log.error("scenario %s failed: %s", scenario.name, exc)
    finally:
        rec.cpu_s = procs.cpu_seconds()
        codes = procs.stop_all()
        if progress:
            sys.stderr.write("\n")
    bad = {name: code for name, code in codes.items() if code not in (0, -signal.SIGTERM)}
    if ok and bad:
        ok, failure = False, f"processes exited with errors: {bad}"
    qod_file = folder / "qod.json"  # the operator's sessions once every process stopped (camara backend)
    rec.qod = json.loads(qod_file.read_text()) if qod_file.exists() else None
    return ok, failure


@dataclass(frozen=True, slots=True)
class Streams:
    """What the recorder's own session hears of the drone, as a ground station would."""

    states: BoundedQueue[Received]
    refs: BoundedQueue[Received]
    status: BoundedQueue[Received]

    @classmethod
    def subscribe(cls, bus: Bus, uav: str = UAV) -> Streams:
        streams = cls(BoundedQueue(QUEUE_ITEMS), BoundedQueue(QUEUE_ITEMS), BoundedQueue(QUEUE_ITEMS))
        bus.subscribe(keys.uplink_any_flow(uav, Stream.STATE), streams.states, expect=(State,))
        bus.subscribe(keys.downlink(uav, Downlink.REFERENCE), streams.refs, expect=(Reference,))
        bus.subscribe(keys.uplink_any_flow(uav, Stream.STATUS), streams.status, expect=(SupervisorStatus,))
        return streams

    def drain_into(self, rec: Recording) -> None:
        """Into the recording, each message once: a recorder connected to two sites' routers hears a
        drone on two paths twice (the first arrival is kept)."""
        seen: set[tuple[object, ...]] = set()
        for item in self.states.drain():
            if isinstance(item.message, State) and _first(seen, ("state", item.message.seq)):
                rec.states.append((millis(item.arrival_ns - item.message.stamp_ns), item.message))
        rec.refs = [
            i.message
            for i in self.refs.drain()
            if isinstance(i.message, Reference)
            and _first(seen, ("ref", i.message.replica, i.message.term, i.message.seq))
        ]
        rec.status = [
            i.message
            for i in self.status.drain()
            if isinstance(i.message, SupervisorStatus) and _first(seen, ("status", i.message.seq))
        ]


def _first(seen: set[tuple[object, ...]], key: tuple[object, ...]) -> bool:
    if key in seen:
        return False
    seen.add(key)
    return True


def wait_for_offload(
    states: BoundedQueue[Received], procs: Processes, stop: threading.Event, name: str = "onboard"
) -> int:
    """The stamp of the first state the drone sends in offboard mode: the flight's time zero. The
    states before it are dropped; those after it stay queued for the recording."""
    deadline = time.monotonic() + OFFLOAD_TIMEOUT_S
    while time.monotonic() < deadline and not stop.is_set():
        item = states.get(0.5)
        if item is not None and isinstance(item.message, State) and item.message.mode == OFFBOARD:
            return item.message.stamp_ns
    raise DynqosError(f"{name}: the drone never started offloading: {procs.tail(name)}")


def fly(
    scenario: Scenario,
    procs: Processes,
    cell_port: int,
    injector: FaultInjector,
    rec: Recording,
    stop: threading.Event,
    progress: bool,
    more_cells: Mapping[str, int] | None = None,
) -> None:
    """The recorded flight: faults begin and end on time, memory and the cell's counters are sampled
    (`more_cells`: site -> the control port of that site's cell, a second cell's, sampled beside)."""
    next_poll = next_memory = next_cpu = time.monotonic()
    end = time.monotonic() + scenario.duration_s
    rec.flight_start_ns = round((end - scenario.duration_s) * 1e9)  # time.monotonic's clock, in ns
    pending = sorted(scenario.faults, key=lambda fault: fault.at_s)
    active: list[FaultWindow] = []
    while time.monotonic() < end and not stop.is_set():
        elapsed = scenario.duration_s - (end - time.monotonic())
        while pending and elapsed >= pending[0].at_s:
            active.append(injector.begin(pending.pop(0)))
        for window in [w for w in active if elapsed >= w.fault.at_s + w.fault.duration_s]:
            injector.end(window)
            active.remove(window)
        if time.monotonic() >= next_memory:
            next_memory += scenario.memory_sample_s
            _sample_memory(procs, rec, elapsed)
        if time.monotonic() >= next_cpu:
            next_cpu += MACHINE_SAMPLE_S
            _sample_machine(rec, elapsed)
        _record_tick(scenario, rec, procs, cell_port, elapsed, progress)
        if time.monotonic() >= next_poll:
            next_poll += CELL_POLL_S
            for site, port in {"": cell_port, **(more_cells or {})}.items():
                counters = get_json(port, "/counters")
                counters["now_ns"] = time.monotonic_ns()
                (rec.more_cells.setdefault(site, []) if site else rec.cell).append(counters)
        stop.wait(RECORD_PERIOD_S)
    _sample_machine(rec, scenario.duration_s - (end - time.monotonic()))  # the flight's last second


def _sample_machine(rec: Recording, elapsed: float) -> None:
    cpus, quota = own_machine()
    rec.cores = usable_core_count()  # the reports read it from the recording, not from the host
    times = read_cpu_times(cpus=cpus, quota=quota)
    if times is not None:
        rec.cpu_times.append((elapsed, times))


def _sample_memory(procs: Processes, rec: Recording, elapsed: float) -> None:
    for name, proc in procs.procs.items():
        if name not in procs.down and (memory := resident_memory(proc.pid)) is not None:
            rec.memory_kb.setdefault(name, []).append((elapsed, memory.rss_kb, memory.anon_kb))


def _record_tick(
    scenario: Scenario, rec: Recording, procs: Processes, cell_port: int, elapsed: float, progress: bool
) -> None:
    """The recorder's duties each tick: start the background load, fail on a dead process."""
    if scenario.bg_start_s >= 0 and rec.bg_on_ns is None and elapsed >= scenario.bg_start_s:
        post_json(
            cell_port, "/events", {"kind": "background", "user": "bg", "offered_mbps": scenario.bg_mbps}
        )
        rec.bg_on_ns = time.monotonic_ns()
    dead = procs.dead()
    if dead:
        raise DynqosError(f"{dead[0]} exited during the run: {procs.tail(dead[0])}")
    if progress:
        _progress(scenario, elapsed, rec)


def _progress(scenario: Scenario, elapsed: float, rec: Recording) -> None:
    width = 30
    done = min(width, int(width * elapsed / scenario.duration_s))
    last = rec.cell[-1] if rec.cell else None
    bar = "#" * done + "." * (width - done)
    line = f"\r{scenario.name:<14} [{bar}] {elapsed:5.1f}/{scenario.duration_s:.0f} s"
    if last:
        bearers = last["bearers"]
        delays = max(b["queue_delay_ms"] for b in bearers.values())
        bg = "on" if rec.bg_on_ns else "off"
        line += f"  background {bg}, drone queue {delays:6.1f} ms"
    if sys.stderr.isatty():
        sys.stderr.write(line)
        sys.stderr.flush()
    elif int(elapsed // PROGRESS_EVERY_S) != int((elapsed - RECORD_PERIOD_S) // PROGRESS_EVERY_S):
        log.info("%s", line.replace(f"[{bar}] ", "").strip())  # not a terminal: a log line now and then
