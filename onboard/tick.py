"""What goes into one tick of the onboard core (what the shell read) and what comes out (what the shell
writes): the seam between onboard/core.py and onboard/daemon.py."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from dynqos.common.bus import Received
from dynqos.common.keys import Stream
from dynqos.common.messages import Message
from dynqos.common.modes import Flow
from dynqos.onboard.fc import FcSaid, FcState, Setpoint
from dynqos.onboard.modem import ModemReading
from dynqos.onboard.tasks import TaskJobs, TaskSent, TaskSteer


@dataclass
class Counters:
    """What the onboard core has counted since it started."""

    states: int = 0
    setpoints: int = 0
    fallback_ticks: int = 0
    edge_ticks: int = 0
    frames: int = 0
    camera_bytes: int = 0  # encoded image bytes handed to the bus (headers not counted)
    uplink_bytes: int = 0  # every encoded message on the uplink (camera, state, status, QoS request)
    switches_to_fallback: int = 0
    detections: int = 0


@dataclass(frozen=True, slots=True)
class FrameSent:
    """One image (both its parts if paced) handed to the bus by the camera pipeline."""

    seq: int
    kind: str
    stamp_ns: int
    nbytes: int  # encoded image bytes, message headers not counted


@dataclass(frozen=True, slots=True, kw_only=True)
class TickInput:
    """What the shell read since the last tick. `offboard` turns True once the FC flies offboard."""

    now_ns: int
    fc: FcState | None
    downlink: Sequence[Received] = ()
    frames_sent: Sequence[FrameSent] = ()
    spaciousness_m: float | None = None
    offboard: bool = False
    uplink_bytes: int | None = None  # every byte the drone's publishers put so far (None: unknown)
    modem: ModemReading | None = None  # the modem's newest reading (None: no modem, or none yet)
    fc_said: FcSaid | None = None  # what the FC said last (None: nothing yet)
    task_sent: Sequence[TaskSent] = ()  # the tasks' requests sent (or skipped) since the last tick
    task_steers: Sequence[TaskSteer] = ()  # what the tasks' onboard sides made since the last tick


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One message for the bus: on every path (`path` ""), or on the one path named. Each path sends it
    on `flow`, or on the flow `path_flows` names for that path (a drone with two paths, whose paths
    each have their own PFSM: docs/supervisor.md)."""

    stream: Stream
    flow: Flow
    message: Message
    path: str = ""
    path_flows: tuple[tuple[str, Flow], ...] = ()

    def flow_on(self, path: str) -> Flow:
        for name, flow in self.path_flows:
            if name == path:
                return flow
        return self.flow


@dataclass(frozen=True, slots=True)
class LogEvent:
    level: int  # a `logging` level
    text: str


@dataclass(frozen=True, slots=True)
class TickOutput:
    setpoint: Setpoint | None  # what the FC gets this tick; None before offboard or with no FC state
    publish: tuple[Outgoing, ...]
    camera_flow: Flow
    camera_rate_factor: float
    events: tuple[LogEvent, ...]
    camera_path: str = ""  # the path the camera rides (docs/multipath.md; "" = the only one)
    task_jobs: TaskJobs = field(
        default_factory=TaskJobs
    )  # what the tasks' threads run next (docs/offload.md)
