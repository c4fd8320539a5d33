"""From the fleet's config to its plan's inputs, and from a plan to what the service sends: each drone's
missions (waypoints in local NED) with the mission time each is due. Pure.

A fly leg or a route is one MissionRequest, sent when the leg starts; the planner replicas fly it from
its first waypoint and hold the last, so a time on station (an inspection, a hold) needs no message: it
is the time until the drone's next leg is sent.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from dynqos.common.config import FleetPlanConfig
from dynqos.edge.planner.fleet_plan import Plan, PlanDrone, PlanSettings, Task

Ned = tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class TimedMission:
    at_s: float  # seconds from the mission's start
    uav: str
    waypoints_m: tuple[Ned, ...]  # local NED
    task: str  # the task this leg leads to, or flies (a route)


def tasks_of(cfg: FleetPlanConfig) -> list[Task]:
    return [Task(t.id, t.kind, tuple(t.points_m), t.duration_s, t.risk) for t in cfg.tasks]


def settings_of(cfg: FleetPlanConfig) -> PlanSettings:
    return PlanSettings(
        half_m=cfg.half_m,
        grid_m=cfg.grid_m,
        heights_m=cfg.heights_m,
        nc_cost=cfg.nc_cost,
        mc_cost=cfg.mc_cost,
        bad_weight_s=cfg.bad_weight_s,
        max_bookings=cfg.max_bookings,
        booking_radius_m=cfg.booking_radius_m,
    )


def drones_at(positions: dict[str, Ned], speed_mps: float) -> list[PlanDrone]:
    """The fleet where each drone is (NED), in a stable order."""
    return [PlanDrone(uav, (pos[0], pos[1]), speed_mps) for uav, pos in sorted(positions.items())]


def _ned(points: tuple[tuple[float, float, float], ...]) -> tuple[Ned, ...]:
    """(x, y, height) as NED, without repeated points."""
    out: list[Ned] = []
    for x, y, h in points:
        p = (round(x, 3), round(y, 3), round(-h, 3))
        if not out or math.dist(out[-1], p) > 1e-6:
            out.append(p)
    return tuple(out)


def missions_of(plan: Plan) -> list[TimedMission]:
    """Every leg that moves a drone, as the mission to send and when, in time order."""
    out = []
    for uav, legs in plan.legs.items():
        for leg in legs:
            points = _ned(leg.path_m)
            if len(points) >= 2:  # a leg that goes nowhere (already there, or on station) sends nothing
                out.append(TimedMission(leg.start_s, uav, points, leg.task))
    return sorted(out, key=lambda m: (m.at_s, m.uav))


def path_length(points: tuple[Ned, ...]) -> float:
    return sum(math.dist(a, b) for a, b in itertools.pairwise(points))
