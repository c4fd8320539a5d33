"""A flight's faults as data: what the scenario asks for (`Fault`) and what happened when it was
injected (`FaultWindow`). dynqos/experiment/faults.py injects them; dynqos/reports reads the windows."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from dynqos.common.errors import ConfigError

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
    # (began, ready) in monotonic ns: each time the fault's start or end (re)started processes
    restarts: list[tuple[int, int]] = field(default_factory=list)
