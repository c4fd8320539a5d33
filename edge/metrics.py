"""What each edge service exposes to Prometheus (docs/observability.md): the counters of its health
line, read at scrape time, and the histograms its work feeds."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client.core import CounterMetricFamily, Metric

from dynqos.common.metrics import (
    SOLVE_BUCKETS,
    ProcessMetrics,
    bus_families,
    counter,
    gauge,
    labelled_counter,
)

if TYPE_CHECKING:  # the services import this module, not the other way round
    from dynqos.edge.detector.service import DetectorService
    from dynqos.edge.mpc.service import MpcService
    from dynqos.edge.planner.fleet_service import FleetPlannerService
    from dynqos.edge.planner.service import PlannerService
    from dynqos.edge.qos.agent import QosAgent
    from dynqos.edge.tasks import TaskService


def mpc(service: MpcService, m: ProcessMetrics) -> None:
    service.solve_seconds = m.histogram(
        "dynqos_mpc_solve_seconds",
        "time of each solve: a batch of drones, or one drone by OSQP",
        SOLVE_BUCKETS,
    )

    def families() -> Iterator[Metric]:
        c = service.counters
        yield gauge("dynqos_mpc_drones", "Drones this MPC serves (its shard)", len(service.controllers))
        yield gauge(
            "dynqos_mpc_drones_flying",
            "Drones this replica flies now (not those it stands by for): what the autoscaler reads",
            service.flying(),
        )
        yield counter("dynqos_mpc_states", "States taken in for this shard", c.states)
        yield counter("dynqos_mpc_commands", "Commands published", c.commands)
        yield counter("dynqos_mpc_stale_states", "States skipped for a newer one", c.stale)
        yield counter("dynqos_mpc_solve_failures", "Solves that failed (no command sent)", c.solve_failures)
        yield counter(
            "dynqos_mpc_queue_drops", "Messages dropped by the full input queue", service.inbox.dropped
        )
        yield from bus_families(service.bus)

    m.add(families)


def planner(service: PlannerService, m: ProcessMetrics) -> None:
    def families() -> Iterator[Metric]:
        yield gauge("dynqos_planner_drones", "Drones with a mission", len(service.started_ns))
        yield counter("dynqos_planner_references", "References published", service.sent)
        yield from bus_families(service.bus)

    m.add(families)


def fleet_planner(service: FleetPlannerService, m: ProcessMetrics) -> None:
    def families() -> Iterator[Metric]:
        yield gauge(
            "dynqos_fleet_planner_drones_heard",
            "Drones of the fleet heard in offboard mode",
            len(service.positions),
        )
        yield counter("dynqos_fleet_planner_missions", "Missions (legs) sent to the planners", service.sent)
        yield gauge(
            "dynqos_fleet_planner_bookings", "Bookings made and not released", service.bookings_held()
        )
        yield from bus_families(service.bus)

    m.add(families)


def detector(service: DetectorService, m: ProcessMetrics) -> None:
    service.detect_seconds = m.histogram(
        "dynqos_detector_detect_seconds", "Circle detection time per image", (*SOLVE_BUCKETS, 0.2, 0.5)
    )

    def families() -> Iterator[Metric]:
        yield labelled_counter(
            "dynqos_detector_events",
            "Frames, acks, detections, drops and bad frames",
            "event",
            dict(service.counters),
        )
        yield counter(
            "dynqos_detector_incomplete_frames", "Images missing a part", service.assembler.incomplete
        )
        yield from bus_families(service.bus)

    m.add(families)


def qos(agent: QosAgent, m: ProcessMetrics) -> None:
    def families() -> Iterator[Metric]:
        sessions = sum(r.grant.session is not None for r in agent.drones.values())
        holders = len(agent.arbiter.holders) if agent.arbiter is not None else sessions
        yield gauge("dynqos_qos_drones", "Drones that asked the agent", len(agent.drones))
        yield gauge("dynqos_qos_sessions", "Quality-on-Demand sessions held", sessions)
        yield gauge("dynqos_qos_holders", "Drones granted the priority flow", holders)
        yield labelled_counter(
            "dynqos_qos_decisions",
            "Arbiter decisions by action",
            "action",
            {action.value: n for action, n in agent.decisions.items()},
        )
        yield counter("dynqos_qos_errors", "Operator API errors", agent.errors)
        yield gauge(
            "dynqos_qos_active",
            "1 while this agent holds the sessions, 0 standing by",
            int(agent.leadership.is_active),
        )
        yield counter(
            "dynqos_qos_takeovers", "Times this agent became the active one", agent.leadership.takeovers
        )
        calls = agent.client.calls if agent.client is not None else 0
        yield counter("dynqos_qos_api_calls", "Operator API calls", calls)
        yield from bus_families(agent.bus)

    m.add(families)


def task(service: TaskService, m: ProcessMetrics) -> None:
    """A user's task (docs/offload.md): its calls and each kind of failure, labelled by the task."""

    def families() -> Iterator[Metric]:
        family = CounterMetricFamily(
            "dynqos_task_events",
            "A task's requests, answers, drops and failures (raised, bad_answers, late, hung, bad_requests)",
            labels=["task", "event"],
        )
        for event, n in sorted(service.counters.items()):
            family.add_metric([service.task.name, event], n)
        yield family
        yield from bus_families(service.bus)

    m.add(families)
