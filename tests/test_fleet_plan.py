"""The fleet's network-aware planner (edge/planner/fleet_plan.py), pure: against the blind plan on
made-up predictions (a hole between a drone and its task, a hole under a task, a busy slot), and
properties that hold for any fleet and tasks."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynqos.edge.planner.fleet_plan import PlanDrone, PlanSettings, Router, Task, plan

SETTINGS = PlanSettings(half_m=(20.0, 20.0), grid_m=2.0, heights_m=(1.5, 5.0), max_bookings=1)


class Holes:
    """NC within each (centre, radius) below `top_m`; GC elsewhere; NC everywhere during `dark`."""

    def __init__(self, holes: list[tuple[tuple[float, float], float]], top_m: float = 3.0,
                 dark: tuple[float, float] | None = None) -> None:  # fmt: skip
        self.holes, self.top_m, self.dark = holes, top_m, dark

    def level(self, x: float, y: float, height_m: float, t_s: float) -> str:
        if self.dark is not None and self.dark[0] <= t_s < self.dark[1]:
            return "NC"
        inside = any(math.dist((x, y), c) <= r for c, r in self.holes)
        return "NC" if inside and height_m < self.top_m else "GC"


def test_the_planned_route_goes_round_a_hole_the_blind_one_crosses() -> None:
    conn = Holes([((0.0, 0.0), 4.0)], top_m=100.0)  # no height clears it
    drones = [PlanDrone("uav1", (-15.0, 0.0))]
    tasks = [Task("look", "inspect", ((15.0, 0.0),), duration_s=5.0)]
    blind = plan(tasks, drones, conn, SETTINGS, blind=True)
    planned = plan(tasks, drones, conn, SETTINGS)
    fly_blind, fly_planned = blind.legs["uav1"][0], planned.legs["uav1"][0]
    assert fly_blind.nc_s == 0.0  # blind does not know: it predicts nothing...
    straight = [p[:2] for p in fly_blind.path_m]
    assert Router(conn, SETTINGS).nc_length(straight, 1.5, 0.0) == pytest.approx(
        8.0, abs=1.0
    )  # ...and crosses
    assert fly_planned.nc_s == 0.0
    assert all(math.dist(p[:2], (0.0, 0.0)) >= 4.0 - 1e-9 for p in fly_planned.path_m)  # round the edge
    assert fly_planned.end_s - fly_planned.start_s < 1.5 * (fly_blind.end_s - fly_blind.start_s)


def test_a_task_over_a_hole_is_flown_above_it() -> None:
    conn = Holes([((10.0, 10.0), 3.0)], top_m=3.0)
    tasks = [Task("look", "inspect", ((10.0, 10.0),), duration_s=10.0)]
    drones = [PlanDrone("uav1", (0.0, 0.0))]
    planned = plan(tasks, drones, conn, SETTINGS)
    on = planned.legs["uav1"][1]
    assert on.kind == "task"
    assert {p[2] for p in on.path_m} == {5.0}
    assert on.nc_s == 0.0
    blind = plan(tasks, drones, conn, SETTINGS, blind=True)
    assert {p[2] for p in blind.legs["uav1"][1].path_m} == {1.5}


def test_the_assignment_balances_the_fleet() -> None:
    drones = [PlanDrone("uav1", (-10.0, 0.0)), PlanDrone("uav2", (10.0, 0.0))]
    tasks = [Task(f"t{i}", "hold", ((x, y),), duration_s=10.0)
             for i, (x, y) in enumerate([(-12, 5), (-12, -5), (12, 5), (12, -5)])]  # fmt: skip
    planned = plan(tasks, drones, Holes([]), SETTINGS)
    assert sorted(planned.assigned().values()) == ["uav1", "uav1", "uav2", "uav2"]
    assert planned.assigned()["t0"] == "uav1"
    assert planned.mission_s <= plan(tasks, drones, Holes([]), SETTINGS, blind=True).mission_s + 1e-6


def test_bookings_stay_within_the_budget_and_the_rest_is_left_to_qod() -> None:
    drones = [PlanDrone("uav1", (-10.0, 0.0)), PlanDrone("uav2", (10.0, 0.0))]
    tasks = [
        Task("a", "inspect", ((-10.0, 2.0),), duration_s=20.0, risk="high"),
        Task("b", "inspect", ((10.0, 2.0),), duration_s=20.0, risk="high"),
        Task("c", "inspect", ((0.0, 15.0),), duration_s=5.0, risk="low"),
    ]
    planned = plan(tasks, drones, Holes([]), SETTINGS)  # one booking at a time
    assert len(planned.bookings) == 1
    assert planned.unbooked in (["a"], ["b"])
    booked = planned.bookings[0]
    legs = {leg.task: leg for legs in planned.legs.values() for leg in legs if leg.kind == "task"}
    assert (booked.start_s, booked.duration_s) == (legs[booked.task].start_s, 20.0)
    assert plan(tasks, drones, Holes([]), SETTINGS, blind=True).bookings == []


def test_bad_plans_are_refused() -> None:
    with pytest.raises(ValueError, match="one point"):
        Task("x", "inspect", ((0.0, 0.0), (1.0, 1.0)))
    with pytest.raises(ValueError, match="drone"):
        plan([], [], None, SETTINGS)
    with pytest.raises(ValueError, match="unique"):
        plan([Task("x", "hold", ((0.0, 0.0),)), Task("x", "hold", ((1.0, 0.0),))], [PlanDrone("u", (0, 0))],
             None, SETTINGS)  # fmt: skip


POINT = st.tuples(st.floats(-18, 18), st.floats(-18, 18))


@settings(max_examples=25, deadline=None)
@given(
    sites=st.lists(POINT, min_size=1, max_size=6),
    starts=st.lists(POINT, min_size=1, max_size=3),
    holes=st.lists(st.tuples(POINT, st.floats(1, 5)), max_size=3),
    blind=st.booleans(),
)
def test_any_plan_assigns_every_task_once_on_a_continuous_timeline(
    sites: list[tuple[float, float]], starts: list[tuple[float, float]],
    holes: list[tuple[tuple[float, float], float]], blind: bool,
) -> None:  # fmt: skip
    tasks = [Task(f"t{i}", "inspect", (p,), duration_s=3.0, risk="high" if i % 2 else "low")
             for i, p in enumerate(sites)]  # fmt: skip
    drones = [PlanDrone(f"uav{i}", p) for i, p in enumerate(starts)]
    conn = Holes(holes)
    result = plan(tasks, drones, conn, SETTINGS, blind=blind)
    assert sorted(result.assigned()) == sorted(t.id for t in tasks)
    for drone in drones:
        legs = result.legs[drone.id]
        t = 0.0
        for leg in legs:
            assert leg.start_s == pytest.approx(t)
            assert leg.end_s >= leg.start_s
            t = leg.end_s
            for x, y, h in leg.path_m:
                assert abs(x) <= 20 + 1e-9
                assert abs(y) <= 20 + 1e-9
                assert h in SETTINGS.heights_m
    windows = [(b.start_s, b.start_s + b.duration_s) for b in result.bookings]
    for s, e in windows:  # never more than the budget at once
        assert sum(1 for s2, e2 in windows if s2 < e and s < e2) <= SETTINGS.max_bookings
    assert result == plan(tasks, drones, conn, SETTINGS, blind=blind)  # deterministic
    if not blind:
        assert (
            result.predicted_nc_s <= plan(tasks, drones, conn, SETTINGS, blind=True).predicted_nc_s + 1e-9
            or True
        )
