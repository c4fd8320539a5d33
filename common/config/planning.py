"""Config of the fleet's mission planner ([fleet_plan], `dynqos edge fleet-planner`, docs/planning.md).

The mission is a list of tasks (inspect a point for a time, hold a station, fly a route) for the drones
it names; `mode` says whether the plan uses the operator's predicted connectivity and bookings
(`planned`) or ignores the network (`blind`: greedy, straight, priority asked on demand only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from dynqos.common.config.validate import In, _require, checked
from dynqos.common.keys import UAV_ID_PATTERN


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class FleetTaskConfig:
    """[[fleet_plan.tasks]]: one task of the mission, in local metres (x north, y east)."""

    id: str
    kind: Literal["inspect", "route", "hold"] = "inspect"
    points_m: tuple[tuple[float, float], ...] = ()  # inspect, hold: one point; route: two or more
    duration_s: Annotated[float, In(0, 3600, "must be in 0..3600 s")] = 10.0  # on station
    risk: Literal["high", "low"] = "low"  # a high-risk inspection is worth booking priority for

    def __post_init__(self) -> None:
        ok = UAV_ID_PATTERN.fullmatch(self.id) is not None
        _require(ok, "id", "1 to 32 characters from A-Z a-z 0-9 _ -")
        if self.kind == "route":
            _require(len(self.points_m) >= 2, "points_m", "a route needs two or more points")
        else:
            _require(len(self.points_m) == 1, "points_m", f"an {self.kind} task takes exactly one point")


@dataclass(frozen=True, slots=True, kw_only=True)
@checked
class FleetPlanConfig:
    """[fleet_plan]: the mission's tasks, the drones that share them and how the plan is made."""

    mode: Literal["planned", "blind"] = "planned"
    drones: tuple[str, ...] = ()  # the fleet: the plan starts once each has been heard in offboard mode
    tasks: tuple[FleetTaskConfig, ...] = ()
    wait_s: Annotated[float, In(1, 3600, "must be in 1..3600 s")] = 120.0  # for the drones, then it fails
    # from the plan to the mission's start: time to ask for the prediction and book ahead of it
    lead_s: Annotated[float, In(0.5, 600, "must be in 0.5..600 s")] = 3.0
    speed_mps: Annotated[float, In(0.1, 20, "must be in 0.1..20 m/s")] = 1.0
    half_m: tuple[float, float] = (20.0, 20.0)  # the arena the routes stay in: |x| <= half_x, |y| <= half_y
    grid_m: Annotated[float, In(0.5, 100, "must be in 0.5..100 m")] = 2.0
    heights_m: tuple[float, ...] = (1.5, 5.0)  # above the ground; the first is the default (and blind's)
    nc_cost: Annotated[float, In(1, 1e4, "must be in 1..10000")] = 20.0
    mc_cost: Annotated[float, In(1, 1e4, "must be in 1..10000")] = 2.0
    bad_weight_s: Annotated[float, In(0, 1e4, "must be in 0..10000 s")] = 5.0
    max_bookings: Annotated[int, In(0, 1000, "must be in 0..1000")] = 2  # windows at once: the arbiter's
    booking_radius_m: Annotated[float, In(1, 10_000, "must be in 1..10000 m")] = 3.0
    service_level: str = "C2"  # what the prediction is asked for (the API's serviceLevel)
    precision: Annotated[int, In(1, 12, "must be a geohash level in 1..12")] = 9
    # an answer for a whole arena at a fine level is megabytes: longer than a QoD call's [qos.camara] time-out
    prediction_timeout_s: Annotated[float, In(0.5, 600, "must be in 0.5..600 s")] = 20.0
    # where the local origin is on the earth, as the operator's prediction and bookings speak degrees
    origin_lat_deg: Annotated[float, In(-80, 80, "must be in -80..80 degrees")] = 45.0
    origin_lon_deg: Annotated[float, In(-180, 180, "must be in -180..180 degrees")] = 10.0
    plan_file: str = ""  # where the plan and what became of it is written as JSON ("": nowhere)
    health_interval_s: Annotated[float, In(0.5, 3600, "must be in 0.5..3600 s")] = 5.0

    def __post_init__(self) -> None:
        for uav in self.drones:
            _require(UAV_ID_PATTERN.fullmatch(uav) is not None, "drones", f"{uav!r} is not a drone id")
        _require(len(set(self.drones)) == len(self.drones), "drones", "drone ids must be unique")
        ids = [t.id for t in self.tasks]
        _require(len(set(ids)) == len(ids), "tasks", "task ids must be unique")
        _require(
            bool(self.heights_m) and all(0.3 <= h <= 120 for h in self.heights_m),
            "heights_m",
            "needs one or more heights in 0.3..120 m",
        )
        _require(all(0 < h <= 10_000 for h in self.half_m), "half_m", "must be positive")
        for task in self.tasks:
            for x, y in task.points_m:
                _require(
                    abs(x) <= self.half_m[0] and abs(y) <= self.half_m[1],
                    f"tasks.{task.id}",
                    f"({x:g}, {y:g}) is outside the arena (half_m {self.half_m})",
                )
