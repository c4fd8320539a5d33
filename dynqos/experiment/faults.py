"""Faults a scenario can inject into a loopback flight, and what each did to the drone.

A scenario's `[[scenario.faults]]` list (docs/reliability.md) says when each fault starts and how long
it lasts. The injector acts only on what the run itself started: processes by their pid (SIGKILL and a
restart, SIGSTOP/SIGCONT), the cell emulator through its control API, and a flood of camera frames
from the recorder's own session. The outcome of each fault is measured from the drone's status stream
(SupervisorStatus carries who flies, since when, and the age of the last valid command then): how long
after its last valid command the fallback took over, the longest pause in setpoints to the flight
controller, and how long after the fault cleared control was back at the edge.
"""

from __future__ import annotations

import itertools
import logging
import math
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from dynqos.common import keys
from dynqos.common.bus import Bus, Received
from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.errors import ConfigError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import QosGrant, Reference, State, SupervisorStatus
from dynqos.common.modes import ControlSource
from dynqos.common.queues import BoundedQueue
from dynqos.experiment.processes import Processes

if TYPE_CHECKING:
    from dynqos.experiment.sites import SiteFaults

log = logging.getLogger(__name__)
SETTLE_S = 10.0  # how long after a fault cleared its outcome is looked for (zenoh reconnects take seconds)

FaultKind = Literal[
    "mpc_kill",
    "router_kill",
    "coverage_loss",
    "downlink_loss",
    "fc_silence",
    "detector_flood",
    "background",
    "capacity",
    "trace",
    "mpc_replica_kill",
    "mpc_replica_hang",
    "replica_join",
    "planner_replica_kill",
    "qos_agent_kill",
    "qos_agent_hang",
    "site_kill",
    "cell_outage",
    "path_partition",
    "task_kill",
]
# the faults that SIGKILL processes and restart them when they end; task_kill: every offloaded task's
# edge service (docs/offload.md)
PROCESS_KILLS = {"mpc_kill": "mpc", "router_kill": "router", "task_kill": ""}
SITE_FAULTS = ("site_kill", "cell_outage", "path_partition")  # dynqos/experiment/sites.py acts on them
FLOOD_FPS = 100.0  # several times what the detector can process
FLOOD_MAX_FRAMES = 20_000


@dataclass(frozen=True, slots=True, kw_only=True)
class Fault:
    """One fault: `kind` from `at_s` (seconds into the recorded flight) for `duration_s`."""

    at_s: float
    kind: FaultKind
    duration_s: float = 1.0
    offered_mbps: float = 80.0  # background: the load while it lasts
    uplink_mbps: float = 40.0  # capacity: the cell's uplink capacity while it lasts (full scale)
    file: str = ""  # trace: a Mahimahi uplink trace the capacity follows while it lasts
    site: Literal["a", "b"] = "a"  # site_kill, cell_outage, background: the site (and its cell) it hits

    def __post_init__(self) -> None:
        if not 0 <= self.at_s <= 86400:
            raise ConfigError("at_s", "must be in 0..86400 s")
        if not 0.05 <= self.duration_s <= 3600:
            raise ConfigError("duration_s", "must be in 0.05..3600 s")
        if not 0 <= self.offered_mbps <= 1e5:
            raise ConfigError("offered_mbps", "must be in 0..100000 Mbit/s")
        if not 0 <= self.uplink_mbps <= 1e5:
            raise ConfigError("uplink_mbps", "must be in 0..100000 Mbit/s")
        if self.kind == "trace" and not self.file:
            raise ConfigError("file", "a trace fault names its Mahimahi trace file")


@dataclass
class FaultWindow:
    fault: Fault
    start_wall: float
    start_ns: int
    end_wall: float | None = None
    end_ns: int | None = None
    notes: list[str] = field(default_factory=list)
    target: str = ""  # the process a replica fault acted on
    grant: dict[str, Any] | None = None  # qos_agent_kill and _hang: the drone's grant before and after


class Flood:
    """Camera frames for another drone id at FLOOD_FPS from the recorder's session: bounded in count
    and time, stopped at the fault's end."""

    def __init__(self, bus: Bus, duration_s: float) -> None:
        import cv2
        import numpy as np

        from dynqos.common import keys
        from dynqos.common.keys import Flow, Stream
        from dynqos.common.transport import Priority

        image = np.zeros((480, 640, 3), np.uint8)  # a frame of realistic size (~30 kB), with circles to find
        image[:] = np.linspace(40, 200, 640, dtype=np.uint8)[None, :, None]
        for x in (160, 320, 480):
            cv2.circle(image, (x, 240), 60, (20, 140, 240), 12)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        self.jpeg = jpeg.tobytes()
        self.pub = bus.publisher(keys.uplink("flood", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
        self.stop = threading.Event()
        self.sent = 0
        self.deadline = time.monotonic() + duration_s + 1.0
        self.thread = threading.Thread(target=self._run, name="flood", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from dynqos.common.messages import CameraFrame

        period = 1 / FLOOD_FPS
        next_due = time.monotonic()
        while not self.stop.is_set() and self.sent < FLOOD_MAX_FRAMES and time.monotonic() < self.deadline:
            self.sent += 1
            frame = CameraFrame(
                uav="flood",
                seq=self.sent,
                stamp_ns=time.monotonic_ns(),
                kind="rgb",
                encoding="jpeg",
                width=640,
                height=480,
                intrinsics=(500.0, 500.0, 320.0, 240.0),
                payload=self.jpeg,
            )
            self.pub.put(frame)
            next_due += period
            self.stop.wait(max(0.0, next_due - time.monotonic()))  # the flood's rate

    def close(self) -> int:
        self.stop.set()
        self.thread.join(timeout=5)
        self.pub.close()
        return self.sent


class FaultInjector:
    """Starts and ends faults on a running scenario's processes and cell."""

    def __init__(
        self,
        procs: Processes,
        cell_event: Callable[[dict[str, Any]], object],
        bus: Bus,
        *,
        uplink_mbps: float = 81.3,
        watch_uav: str | None = None,
        sites: SiteFaults | None = None,
    ) -> None:
        """`watch_uav`: the drone whose MPC replica the replica faults act on (the one flying it, from the
        drone's own State), watched from the start when a scenario has such faults."""
        self.procs = procs
        self.cell_event = cell_event  # POST /events to the cell emulator
        self.sites = sites  # the faults that name a site (and its cell), each site's own
        self.bus = bus
        self.uplink_mbps = uplink_mbps  # the cell's configured capacity, restored when a capacity fault ends
        self.windows: list[FaultWindow] = []
        self._floods: dict[int, Flood] = {}
        self._states: BoundedQueue[Received] = BoundedQueue(64)  # the newest few (the oldest drop)
        self._refs: BoundedQueue[Received] = BoundedQueue(64)
        self._grants: BoundedQueue[Received] = BoundedQueue(64)
        self._joined = 0
        if watch_uav is not None:
            bus.subscribe(keys.uplink_any_flow(watch_uav, Stream.STATE), self._states, expect=(State,))
            bus.subscribe(keys.downlink(watch_uav, Downlink.REFERENCE), self._refs, expect=(Reference,))
            bus.subscribe(keys.downlink(watch_uav, Downlink.QOS_GRANT), self._grants, expect=(QosGrant,))

    def _serving(self, service: str) -> tuple[str, str]:
        """The process of `service` (mpc, planner) serving the watched drone: the MPC replica its latest
        State says it follows, the planner replica that sent its latest Reference; and a note."""
        if service == "mpc":
            states = [i.message for i in self._states.drain() if isinstance(i.message, State)]
            name, term = (states[-1].command_replica, states[-1].command_term) if states else ("", 0)
        else:
            refs = [i.message for i in self._refs.drain() if isinstance(i.message, Reference)]
            name, term = (refs[-1].replica, refs[-1].term) if refs else ("", 0)
        if name in self.procs.procs and name not in self.procs.down:
            return name, f"{name} served the drone (term {term})"
        live = [n for n in self.procs.procs if n.split("-")[0] == service and n not in self.procs.down]
        if not live:
            return "", f"no {service} replica is running: nothing to act on"
        return live[
            0
        ], f"no live {service} replica was seen serving the drone ({name or 'none'}): acted on {live[0]}"

    def _active_agent(self) -> tuple[str, str]:
        """The QoS agent process holding the active token (edge/qos/leadership.py), and a note."""
        tokens = self.bus.alive_tokens(keys.qos_actives("all"), timeout_s=2.0)
        active = sorted(keys.replica_of_token(k) for k in tokens)
        running = [a for a in active if a in self.procs.procs and a not in self.procs.down]
        if not running:
            return "", f"no running QoS agent holds the active token ({', '.join(active) or 'none'})"
        return running[0], f"{running[0]} was the active agent"

    def _begin_agent_fault(self, window: FaultWindow) -> None:
        """SIGKILL (qos_agent_kill) or SIGSTOP (qos_agent_hang) the active agent, its grant noted."""
        grants = [i.message for i in self._grants.drain() if isinstance(i.message, QosGrant)]
        before = grants[-1] if grants else None
        window.grant = {
            "before": before.grant.value if before else None,
            "session_before": before.session_id if before else "",
        }
        window.target, note = self._active_agent()
        window.notes.append(note)
        if window.target and window.fault.kind == "qos_agent_hang":
            self.procs.signal(window.target, signal.SIGSTOP)
        elif window.target:
            self.procs.kill(window.target)

    def _end_agent_fault(self, window: FaultWindow) -> None:
        """The first grant the drone was told after the fault began (the standby's), and when; then the
        killed agent restarted, or the hung one woken (each comes back and stands by)."""
        assert window.grant is not None
        after = next(
            (
                i
                for i in self._grants.drain()
                if isinstance(i.message, QosGrant) and i.arrival_ns > window.start_ns
            ),
            None,
        )
        if after is None:
            window.notes.append("no grant was told while the fault lasted")
            window.grant |= {"after": None, "served_after_s": None, "same_session": False}
        else:
            assert isinstance(after.message, QosGrant)
            window.grant |= {
                "after": after.message.grant.value,
                "served_after_s": round((after.arrival_ns - window.start_ns) / NS_PER_S, 3),
                "same_session": after.message.session_id == window.grant["session_before"],
            }
        if window.target and window.fault.kind == "qos_agent_hang":
            self.procs.signal(window.target, signal.SIGCONT)
        elif window.target:
            self.procs.restart(window.target)

    def _begin_replica_fault(self, window: FaultWindow) -> None:
        kind = window.fault.kind
        if kind == "replica_join":
            self._joined += 1
            window.target = f"mpc-join{self._joined}"
            self.procs.start(window.target, ["edge", "mpc", "--set", f'mpc.replica_id="{window.target}"'])
            window.notes.append(f"{window.target} joined")
            return
        window.target, note = self._serving("planner" if kind == "planner_replica_kill" else "mpc")
        window.notes.append(note)
        if window.target and kind in ("mpc_replica_kill", "planner_replica_kill"):
            self.procs.kill(window.target)
        elif window.target:
            self.procs.signal(window.target, signal.SIGSTOP)

    def begin(self, fault: Fault) -> FaultWindow:
        window = FaultWindow(fault, time.time(), time.monotonic_ns())
        kind = fault.kind
        if self._at_site(fault):
            assert self.sites is not None
            self.sites.begin(window)
        elif kind in PROCESS_KILLS:
            self._kill(window)
        elif kind in ("coverage_loss", "downlink_loss"):
            self.cell_event({"kind": kind, "duration_s": fault.duration_s})
        elif kind == "fc_silence":
            self.procs.signal("vehicle", signal.SIGSTOP)
        elif kind == "detector_flood":
            self._floods[id(window)] = Flood(self.bus, fault.duration_s)
        elif kind == "background":
            self.cell_event({"kind": "background", "user": "bg", "offered_mbps": fault.offered_mbps})
        elif kind == "capacity":
            self.cell_event({"kind": "capacity", "uplink_mbps": fault.uplink_mbps})
        elif kind == "trace":
            self.cell_event({"kind": "trace", "file": str(Path(fault.file).resolve()), "mean_mbps": 0.0})
        elif kind in ("mpc_replica_kill", "mpc_replica_hang", "replica_join", "planner_replica_kill"):
            self._begin_replica_fault(window)
        elif kind in ("qos_agent_kill", "qos_agent_hang"):
            self._begin_agent_fault(window)
        log.info("fault: %s for %.1f s", kind, fault.duration_s)
        self.windows.append(window)
        return window

    def _kill(self, window: FaultWindow) -> None:
        kind = window.fault.kind
        window.target = ",".join(self._task_services() if kind == "task_kill" else [PROCESS_KILLS[kind]])
        for name in filter(None, window.target.split(",")):
            self.procs.kill(name)
        if not window.target:
            window.notes.append("no task service runs: nothing to kill")

    def _task_services(self) -> list[str]:
        return [n for n in self.procs.procs if n.startswith("task-") and n not in self.procs.down]

    def _at_site(self, fault: Fault) -> bool:
        return self.sites is not None and (fault.kind in SITE_FAULTS or fault.site != "a")

    def end(self, window: FaultWindow) -> None:
        kind = window.fault.kind
        if self._at_site(window.fault):
            assert self.sites is not None
            self.sites.end(window)
        elif kind in PROCESS_KILLS:  # restarted, each from its own command line
            for name in filter(None, window.target.split(",")):
                self.procs.restart(name)
        elif kind == "fc_silence":
            self.procs.signal("vehicle", signal.SIGCONT)
        elif kind in ("mpc_replica_kill", "planner_replica_kill") and window.target:
            self.procs.restart(window.target)
        elif kind == "mpc_replica_hang" and window.target:
            self.procs.signal(window.target, signal.SIGCONT)
        elif kind in ("qos_agent_kill", "qos_agent_hang"):
            self._end_agent_fault(window)
        elif kind == "detector_flood":
            flood = self._floods.pop(id(window))
            window.notes.append(f"{flood.close()} flood frames sent")
        elif kind == "background":
            self.cell_event({"kind": "background", "user": "bg", "offered_mbps": 0.0})
        elif kind in ("capacity", "trace"):  # a capacity event also ends trace-driven capacity
            self.cell_event({"kind": "capacity", "uplink_mbps": self.uplink_mbps})
        window.end_wall, window.end_ns = time.time(), time.monotonic_ns()
        log.info("fault cleared: %s", kind)

    def close(self) -> None:
        for window in self.windows:
            if window.end_ns is None:
                self.end(window)


# ---- outcomes ----------------------------------------------------------------------------------------


def time_in_states(
    statuses: Sequence[SupervisorStatus],
    since_ns: int | None = None,
    field: str = "state",
    *,
    within: tuple[int, int] | None = None,
) -> dict[str, float]:
    """Seconds with each value of a status field (the supervisor state by default; `risk`, `flow`...):
    a status's value lasts until the next status. Only the spans that start at or after `since_ns` count
    (all of them when None); with `within` (lo, hi), only the part of each span inside [lo, hi)."""
    out: dict[str, float] = {}
    lo, hi = within or (-math.inf, math.inf)
    for a, b in itertools.pairwise(statuses):
        if since_ns is None or a.stamp_ns >= since_ns:
            value = getattr(a, field)
            key = str(getattr(value, "value", value))
            span = max(0, min(b.stamp_ns, hi) - max(a.stamp_ns, lo))
            out[key] = out.get(key, 0.0) + span / NS_PER_S
    return out


def _while_it_lasted(during: list[SupervisorStatus], start_ns: int) -> dict[str, Any]:
    """What the drone saw and did while the fault lasted: its RTT, its time in each state, and how soon
    its camera was slowed (the rate-adaptation states, q4-q6) after the fault began."""
    rtts = sorted(v for s in during for v in s.rtt_samples_ms)
    states = time_in_states(during)
    slowed = next((s for s in during if s.camera_rate_factor < 1.0), None)
    rtt = None
    if rtts:
        rtt = {"mean": sum(rtts) / len(rtts), "p95": rtts[min(len(rtts) - 1, int(0.95 * len(rtts)))]}
    return {
        "rtt_ms_during": rtt,
        "states_s_during": {k: round(v, 2) for k, v in sorted(states.items())},
        "camera_slowed_after_s": None
        if slowed is None
        else round((slowed.stamp_ns - start_ns) / NS_PER_S, 2),
    }


def _signals(status: SupervisorStatus) -> dict[str, Any]:
    """What the supervisor saw in its last status of the window: why a drone not yet back is not."""
    return {
        "state": status.state.value,
        "latency": status.latency,
        "t_cam_ms": status.t_cam_ms,
        "t_cc_ms": status.t_cc_ms,
        "p_cam": status.p_cam,
        "p_cc": status.p_cc,
        "risk": status.risk,
    }


def log_times(text: str) -> list[tuple[float, str]]:
    """(wall time, message) of each line of a dynqos log (`%(asctime)s LEVEL name: message`)."""
    out = []
    for line in text.splitlines():
        try:
            stamp = datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
        except ValueError:
            continue
        out.append((stamp, line[24:]))
    return out


def _in_fallback_at(status: Sequence[SupervisorStatus], stamp_ns: int) -> SupervisorStatus | None:
    """The drone's last status at or before `stamp_ns` when its fallback was flying it then, else None."""
    before = [s for s in status if s.stamp_ns <= stamp_ns]
    last = max(before, key=lambda s: s.stamp_ns, default=None)
    return last if last is not None and last.control_source is ControlSource.FALLBACK else None


def outcome(
    window: FaultWindow,
    onboard_log: list[tuple[float, str]],
    status: Sequence[SupervisorStatus],
    next_start_ns: int | None,
    tracking_errors: Sequence[tuple[int, float]] = (),
) -> dict[str, Any]:
    """What the fault did, measured from the drone's SupervisorStatus stream: whether control fell back,
    how long after the last valid command, the longest setpoint gap, and when control was back at the
    edge; and from `tracking_errors` ((state stamp, distance to the published reference)) how far the
    drone left its mission. Its window runs from its start to SETTLE_S after it cleared, or to the next
    fault's start. The onboard log only supplies the lines a reader will want to see beside the figures."""
    fault = window.fault
    end_ns = window.end_ns if window.end_ns is not None else window.start_ns + to_ns(fault.duration_s)
    until_ns = end_ns + to_ns(SETTLE_S)
    if next_start_ns is not None:
        until_ns = min(until_ns, next_start_ns)
    seen = sorted((s for s in status if window.start_ns <= s.stamp_ns <= until_ns), key=lambda s: s.stamp_ns)
    at_start = _in_fallback_at(status, window.start_ns)
    fallback = at_start or next(
        (
            s
            for s in seen
            if s.control_source is ControlSource.FALLBACK
            and window.start_ns <= s.control_changed_ns <= end_ns + NS_PER_S
        ),
        None,
    )
    entered = None if at_start else fallback  # fell back in this fault's window, and when
    back = None
    if fallback is not None:
        since = fallback.control_changed_ns
        edge = (s for s in seen if s.control_source is ControlSource.EDGE and s.control_changed_ns > since)
        back = next(edge, None)
    gaps = [s.setpoint_gap_ms for s in seen if s.setpoint_gap_ms is not None]
    errors = [e for t, e in tracking_errors if window.start_ns <= t <= until_ns]
    during = [s for s in seen if s.stamp_ns <= end_ns]
    until_wall = window.start_wall + (until_ns - window.start_ns) / NS_PER_S
    lines = [m for t, m in onboard_log if window.start_wall <= t <= until_wall]
    notable = [m.split(": ", 1)[-1] for m in lines if m.startswith(("WARNING ", "ERROR "))]
    notable += [m.split(": ", 1)[-1] for m in lines if "control from the edge" in m][:1]
    return {
        "kind": fault.kind,
        "at_s": fault.at_s,
        "duration_s": fault.duration_s,
        # flown by its fallback while the fault lasted: fell back in it, or was there when it began (an
        # earlier fault's fallback not yet handed back); the two timings are for a fallback it caused
        "fallback": fallback is not None,
        "fallback_at_start": at_start is not None,
        "fallback_after_last_command_ms": None if entered is None else entered.command_age_ms,
        "fallback_after_fault_s": (
            None if entered is None else round((entered.control_changed_ns - window.start_ns) / NS_PER_S, 3)
        ),
        "max_setpoint_gap_ms": max(gaps) if gaps else None,
        "max_tracking_error_m": max(errors) if errors else None,
        # None: never left the edge (no fallback), or not back within `settle` (see "recovered")
        "back_at_edge_after_clear_s": (
            None if back is None else round(max(0.0, (back.control_changed_ns - end_ns) / NS_PER_S), 3)
        ),
        "recovered": fallback is None or back is not None,
        "at_window_end": _signals(seen[-1]) if seen else None,
        **_while_it_lasted(during, window.start_ns),
        "log": notable[:4],
        "notes": window.notes,
        **({"grant": window.grant} if window.grant is not None else {}),
    }
