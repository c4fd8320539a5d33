"""What the onboard daemon exposes to Prometheus (docs/observability.md).

Everything comes from the SupervisorStatus the core publishes (a few times a second) and the command
tracker's counters, so the 50 Hz loop does no more than hand each status over: the RTT and camera
latency samples since the last status go into histograms, the state and its changes into enum gauges
and a transitions counter by cause.
"""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from dynqos.common.bus import Bus
from dynqos.common.messages import SupervisorStatus
from dynqos.common.metrics import LATENCY_BUCKETS, ProcessMetrics, bus_families, one_of
from dynqos.common.modes import ControlSource, Flow, Grant, SupervisorState
from dynqos.onboard.commands import CommandCounters


class DroneMetrics:
    def __init__(self, uav: str, m: ProcessMetrics, commands: CommandCounters, bus: Bus | None) -> None:
        self.uav = uav
        self.commands = commands
        self.bus = bus
        self.rtt = m.histogram(
            "dynqos_cc_rtt_seconds",
            "Command-and-control round trip, state to command",
            LATENCY_BUCKETS,
            ("uav",),
        ).labels(uav)
        self.camera = m.histogram(
            "dynqos_camera_latency_seconds",
            "Camera frame to its ack from the detector",
            LATENCY_BUCKETS,
            ("uav",),
        ).labels(uav)
        self.last: SupervisorStatus | None = None
        self.statuses = 0
        self.transitions: dict[tuple[str, str, str], int] = {}
        m.add(self.families)

    def observe(self, status: SupervisorStatus) -> None:
        """Take in one published status (the loop's thread; a scrape reads `last` and the counters)."""
        for rtt_ms in status.rtt_samples_ms:
            self.rtt.observe(rtt_ms / 1000)
        for latency_ms in status.camera_latency_samples_ms:
            self.camera.observe(latency_ms / 1000)
        previous = self.last
        if (
            previous is not None
            and status.changed_ns != previous.changed_ns
            and status.state != previous.state
        ):
            key = (status.prev_state.value, status.state.value, status.cause)
            self.transitions[key] = self.transitions.get(key, 0) + 1
        self.last = status
        self.statuses += 1

    def families(self) -> Iterator[Metric]:
        uav = self.uav
        c = self.commands
        accepted = CounterMetricFamily("dynqos_commands_accepted", "Edge commands accepted", labels=["uav"])
        accepted.add_metric([uav], c.accepted)
        yield accepted
        rejected = CounterMetricFamily(
            "dynqos_commands_rejected", "Edge commands refused, by cause", labels=["uav", "cause"]
        )
        for cause in ("stale", "unknown_state", "expired", "future", "wrong_drone"):
            rejected.add_metric([uav, cause], getattr(c, cause))
        yield rejected
        transitions = CounterMetricFamily(
            "dynqos_supervisor_transitions",
            "Supervisor state changes",
            labels=["uav", "from_state", "to_state", "cause"],
        )
        for (before, after, cause), n in sorted(dict(self.transitions).items()):
            transitions.add_metric([uav, before, after, cause], n)
        yield transitions
        status = self.last
        if status is not None:
            yield from self._status_families(status)
        if self.bus is not None:
            yield from bus_families(self.bus)

    def _status_families(self, s: SupervisorStatus) -> Iterator[Metric]:
        uav = self.uav
        yield one_of(
            "dynqos_supervisor_state",
            "The supervisor's state (1: current)",
            "state",
            [q.value for q in SupervisorState],
            s.state.value,
            uav=uav,
        )
        yield one_of(
            "dynqos_flow",
            "The QoS flow of commands and state (1: current)",
            "flow",
            [f.value for f in Flow],
            s.flow.value,
            uav=uav,
        )
        yield one_of(
            "dynqos_camera_flow",
            "The QoS flow of the camera (1: current)",
            "flow",
            [f.value for f in Flow],
            s.camera_flow.value,
            uav=uav,
        )
        yield one_of(
            "dynqos_control_source",
            "Who flies the drone (1: current)",
            "source",
            [c.value for c in ControlSource],
            s.control_source.value,
            uav=uav,
        )
        yield one_of(
            "dynqos_qos_grant",
            "The network's grant of the priority flow (1: current)",
            "grant",
            [g.value for g in Grant],
            s.qos_grant.value,
            uav=uav,
        )
        gauges = (
            ("dynqos_camera_rate_factor", "Camera rate / configured rate", s.camera_rate_factor),
            ("dynqos_latency_probability", "P_lat: the probability that latency is high", s.p_lat),
            (
                "dynqos_setpoint_gap_seconds",
                "Longest pause between setpoints since the last status",
                (s.setpoint_gap_ms or 0.0) / 1000,
            ),
        )
        for name, doc, value in gauges:
            gauge = GaugeMetricFamily(name, doc, labels=["uav"])
            gauge.add_metric([uav], value)
            yield gauge
        counters = (
            ("dynqos_fallbacks", "Hand-overs to the fallback PID", s.fallbacks),
            ("dynqos_camera_sent_bytes", "Camera bytes handed to zenoh, before any drop", s.camera_bytes),
            (
                "dynqos_uplink_sent_bytes",
                "Every uplink message's bytes handed to zenoh, before any drop",
                s.uplink_bytes,
            ),
        )
        for name, doc, total in counters:
            counter = CounterMetricFamily(name, doc, labels=["uav"])
            counter.add_metric([uav], total)
            yield counter
        if s.tasks:
            yield from _task_families(uav, s)


def _task_families(uav: str, s: SupervisorStatus) -> Iterator[Metric]:
    """The user's offloaded tasks (docs/offload.md): calls, answers applied and misses, by task, and
    whether each flies its fallback now."""
    calls = CounterMetricFamily(
        "dynqos_task_calls", "A task's requests, answers applied and misses", labels=["uav", "task", "event"]
    )
    fallback = GaugeMetricFamily(
        "dynqos_task_fallback", "1 while a task flies its fallback", labels=["uav", "task"]
    )
    for name, mode, requests, applied, misses, _fallback_s, _rtts in s.tasks:
        for event, n in (("requests", requests), ("applied", applied), ("misses", misses)):
            calls.add_metric([uav, name, event], n)
        fallback.add_metric([uav, name], 1.0 if mode == "fallback" else 0.0)
    yield calls
    yield fallback
