"""Faults a scenario can inject into a loopback flight (dynqos/reports/outcomes.py says what each did).

A scenario's `[[scenario.faults]]` list (docs/reliability.md) says when each fault starts and how long
it lasts. The injector acts only on what the run itself started: processes by their pid (SIGKILL and a
restart, SIGSTOP/SIGCONT), the cell emulator through its control API, and a flood of camera frames
from the recorder's own session. Each fault's window (when it began and ended, and each restart to its
process's ready line) is all this module keeps: dynqos/reports/outcomes.py measures from the drone's
status stream what it did to the flight.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dynqos.common import keys
from dynqos.common.bus import Bus, Received
from dynqos.common.clock import NS_PER_S
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import QosGrant, Reference, State
from dynqos.common.queues import BoundedQueue
from dynqos.experiment.processes import Processes
from dynqos.plan.faults import PROCESS_KILLS, SITE_FAULTS, Fault, FaultWindow

if TYPE_CHECKING:
    from dynqos.experiment.sites import SiteFaults

log = logging.getLogger(__name__)
FLOOD_FPS = 100.0  # several times what the detector can process
FLOOD_MAX_FRAMES = 20_000


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
        self._noting_restarts(window, self._begin)
        log.info("fault: %s for %.1f s", fault.kind, fault.duration_s)
        self.windows.append(window)
        return window

    def _noting_restarts(self, window: FaultWindow, act: Callable[[FaultWindow], None]) -> None:
        """`act` on the window, noting when it began and when it ended if it (re)started a process: a
        start costs the machine a second or two of CPU (imports, a session), which is the flight's
        own doing, not the host's (dynqos/reports/machine.py keeps those seconds apart)."""
        launched, began = self.procs.launches, time.monotonic_ns()
        act(window)
        if self.procs.launches > launched:
            window.restarts.append((began, time.monotonic_ns()))

    def _begin(self, window: FaultWindow) -> None:
        fault = window.fault
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
        self._noting_restarts(window, self._end)
        window.end_wall, window.end_ns = time.time(), time.monotonic_ns()
        log.info("fault cleared: %s", window.fault.kind)

    def _end(self, window: FaultWindow) -> None:
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

    def close(self) -> None:
        for window in self.windows:
            if window.end_ns is None:
                self.end(window)
