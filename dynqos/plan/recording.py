"""What the scenario runner records of a flight, as a ground station would see it: the drone's states
with their uplink latency, the references, the supervisor's status, the cell's counters, the fault
windows and each process's memory. dynqos/reports/summary.py turns it into the run folder."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from dynqos.common.messages import QosDecision, Reference, State, SupervisorStatus
from dynqos.plan.faults import FaultWindow


@dataclass(frozen=True, slots=True)
class GroupCpu:
    """One reading of the quota group: CPU time used (None: not readable) and time held by the quota,
    in nanoseconds."""

    quota_cores: float
    usage_ns: int | None
    throttled_ns: int


@dataclass(frozen=True, slots=True)
class CpuTimes:
    """The cores' time since boot, in clock ticks: in total, busy (not idle, not waiting on I/O), and
    stolen (the hypervisor ran something else; part of busy); and the quota group's reading, if any."""

    busy: int
    total: int
    steal: int = 0
    group: GroupCpu | None = None


@dataclass
class Recording:
    t0_ns: int = 0
    states: list[tuple[float, State]] = field(default_factory=list)  # (uplink latency ms, state)
    refs: list[Reference] = field(default_factory=list)
    status: list[SupervisorStatus] = field(default_factory=list)
    cell: list[dict[str, Any]] = field(default_factory=list)
    # site -> the counters of that site's cell, for cells beyond the first (docs/multipath.md)
    more_cells: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    bg_on_ns: int | None = None
    offload_ns: int | None = None
    faults: list[FaultWindow] = field(default_factory=list)
    # name -> (t_s, VmRSS kB, RssAnon kB): resident memory with and without the mapped libraries' pages
    memory_kb: dict[str, list[tuple[float, int, int]]] = field(default_factory=dict)
    qod: dict[str, Any] | None = None  # the emulated operator's QoD counters and sessions left at the end
    cpu_s: dict[str, float] = field(default_factory=dict)  # process name -> CPU seconds, read at the end
    cpu_s_t0: dict[str, float] = field(default_factory=dict)  # ... read when the recorded flight began
    # (t_s into the flight, all cores' CPU times) about every second: how busy the machine was
    cpu_times: list[tuple[float, CpuTimes]] = field(default_factory=list)
    cores: int = 1  # the cores the flight's processes could use (its affinity), when it was flown
    flight_start_ns: int | None = None  # monotonic ns at the flight's second 0, which cpu_times count from


@dataclass(slots=True)
class FlightRecords:
    """What a flight recorded: `flight`, what the drones share (the cell, the load, the faults, memory
    and CPU), each drone's own (`drones`; one drone's recording is the flight's itself: a fleet of one),
    and the QoS agents' decisions."""

    flight: Recording
    drones: dict[str, Recording]
    decisions: list[QosDecision] = field(default_factory=list)

    @classmethod
    def of(cls, drones: tuple[str, ...], fleet: bool) -> FlightRecords:
        flight = Recording()
        return cls(flight, {uav: Recording() for uav in drones} if fleet else {drones[0]: flight})

    def on_flight_clock(self, uav: str) -> None:
        """Drone `uav`'s recording as the flight has it: its states from the flight's time zero on,
        the faults and the load of the flight (the same object for one drone: nothing changes)."""
        drone, flight = self.drones[uav], self.flight
        drone.faults, drone.t0_ns, drone.bg_on_ns = flight.faults, flight.t0_ns, flight.bg_on_ns
        drone.states = [(lat, state) for lat, state in drone.states if state.stamp_ns >= flight.t0_ns]
