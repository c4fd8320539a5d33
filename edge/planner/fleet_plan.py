"""Plan a fleet's mission by the network it will meet: who does which task, in what order, along which
route and at what height, and when to book priority. Pure: positions in local metres, times in seconds
from the plan's start, the network as a `Connectivity` (what the operator predicts); no I/O, no clock.

The blind plan is what a fleet does without the network: each task to the drone that can start it
soonest, straight legs at the default height, no bookings (priority asked on demand). The planned one:
- **height**: each task at the height whose predicted level is best at its site (GC over MC over NC);
- **assignment**: a mixed-integer program (scipy's HiGHS) minimising the fleet's makespan plus the
  predicted time without connectivity, each task to exactly one drone;
- **order**: each drone's tasks nearest-first from where it is;
- **routes**: shortest paths on a grid over the arena (scipy's csgraph) where a metre through a cell
  predicted NC costs `nc_cost` metres and MC `mc_cost`, at whichever allowed height crosses the fewest
  metres predicted NC (then the shortest);
- **bookings**: each high-risk inspection booked for its window while fewer than `max_bookings` windows
  overlap it (the arbiter's budget); the rest left to QoD on demand.
scipy is already what the edge installs (OSQP's sparse matrices); OR-Tools would add ~100 MB for a
problem of a handful of drones and tasks.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import dijkstra

Point = tuple[float, float]
IMPROVE_ROUNDS = 200  # moves and swaps that each lowered the objective, at most
RANK = {"GC": 0, "MC": 1, "ND": 2, "NC": 3}  # better first; no data is better than a predicted hole


class Connectivity(Protocol):
    """What the network predicts: a level (GC, MC, NC, ND) at (x, y), a height above ground and a time."""

    def level(self, x: float, y: float, height_m: float, t_s: float) -> str: ...


@dataclass(frozen=True, slots=True)
class Task:
    id: str
    kind: Literal["inspect", "route", "hold"]
    points_m: tuple[Point, ...]  # inspect, hold: the one site; route: the waypoints to fly in order
    duration_s: float = 0.0  # on station (inspect, hold)
    risk: Literal["high", "low"] = "low"  # a high-risk inspection is worth booking priority for

    def __post_init__(self) -> None:
        if not self.points_m or (self.kind != "route" and len(self.points_m) != 1):
            raise ValueError(
                f"task {self.id}: {self.kind} takes {'points' if self.kind == 'route' else 'one point'}"
            )
        if self.duration_s < 0:
            raise ValueError(f"task {self.id}: duration_s must be >= 0")


@dataclass(frozen=True, slots=True)
class PlanDrone:
    id: str
    start_m: Point
    speed_mps: float = 1.0


@dataclass(frozen=True, slots=True)
class PlanSettings:
    half_m: Point = (20.0, 20.0)  # the arena: |x| <= half_x, |y| <= half_y
    grid_m: float = 2.0
    heights_m: tuple[float, ...] = (1.5, 5.0)  # the first is the default (and the blind plan's)
    nc_cost: float = 20.0  # a metre through a cell predicted NC costs this many metres
    mc_cost: float = 2.0
    bad_weight_s: float = 5.0  # the assignment's price of a second predicted without connectivity
    max_bookings: int = 2  # windows booked at once (the arbiter's budget)
    booking_radius_m: float = 3.0
    time_step_s: float = 10.0  # routes are priced once per step of the prediction's time


@dataclass(frozen=True, slots=True)
class Leg:
    """One piece of a drone's timeline: a flight along `path_m` or a task on station."""

    kind: Literal["fly", "task"]
    start_s: float
    end_s: float
    path_m: tuple[tuple[float, float, float], ...]  # (x, y, height above ground)
    task: str = ""
    nc_s: float = 0.0  # predicted seconds in cells without connectivity


@dataclass(frozen=True, slots=True)
class BookingPlan:
    drone: str
    task: str
    start_s: float
    duration_s: float
    center_m: Point
    radius_m: float


@dataclass
class Plan:
    legs: dict[str, list[Leg]] = field(default_factory=dict)
    bookings: list[BookingPlan] = field(default_factory=list)
    unbooked: list[str] = field(default_factory=list)  # high-risk tasks the budget left to QoD on demand

    @property
    def mission_s(self) -> float:
        return max((legs[-1].end_s for legs in self.legs.values() if legs), default=0.0)

    @property
    def predicted_nc_s(self) -> float:
        return sum(leg.nc_s for legs in self.legs.values() for leg in legs)

    def assigned(self) -> dict[str, str]:
        return {leg.task: drone for drone, legs in self.legs.items() for leg in legs if leg.kind == "task"}


# ---- the grid --------------------------------------------------------------------------------------------


class Grid:
    """Nodes every `grid_m` over the arena, 8-connected."""

    def __init__(self, settings: PlanSettings) -> None:
        self.s = settings
        self.nx = int(2 * settings.half_m[0] // settings.grid_m) + 1
        self.ny = int(2 * settings.half_m[1] // settings.grid_m) + 1

    def node(self, p: Point) -> int:
        i = min(self.nx - 1, max(0, round((p[0] + self.s.half_m[0]) / self.s.grid_m)))
        j = min(self.ny - 1, max(0, round((p[1] + self.s.half_m[1]) / self.s.grid_m)))
        return i * self.ny + j

    def point(self, node: int) -> Point:
        i, j = divmod(node, self.ny)
        return (i * self.s.grid_m - self.s.half_m[0], j * self.s.grid_m - self.s.half_m[1])

    def edges(self) -> list[tuple[int, int, float]]:
        out = []
        for i in range(self.nx):
            for j in range(self.ny):
                for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
                    a, b = i + di, j + dj
                    if 0 <= a < self.nx and 0 <= b < self.ny:
                        out.append((i * self.ny + j, a * self.ny + b, math.hypot(di, dj) * self.s.grid_m))
        return out


def _cost(level: str, settings: PlanSettings) -> float:
    return {"NC": settings.nc_cost, "MC": settings.mc_cost}.get(level, 1.0)


class Router:
    """Shortest paths at one height and time, priced by the predicted level of the cells they cross."""

    def __init__(self, conn: Connectivity | None, settings: PlanSettings) -> None:
        self.conn = conn
        self.s = settings
        self.grid = Grid(settings)
        self._edges = self.grid.edges()
        self._matrices: dict[tuple[float, int], csr_matrix] = {}  # (height, time step) -> priced grid
        self._trees: dict[tuple[float, int, int], np.ndarray] = {}  # (height, step, start) -> predecessors

    def level(self, p: Point, height: float, t_s: float) -> str:
        return "GC" if self.conn is None else self.conn.level(p[0], p[1], height, t_s)

    def _matrix(self, height: float, step: int) -> csr_matrix:
        """The grid's edges priced by the level predicted at their middle: once per height and step."""
        key = (height, step)
        if key not in self._matrices:
            t_s = step * self.s.time_step_s
            weights = []
            for a, b, length in self._edges:
                (ax, ay), (bx, by) = self.grid.point(a), self.grid.point(b)
                middle = ((ax + bx) / 2, (ay + by) / 2)
                weights.append(length * _cost(self.level(middle, height, t_s), self.s))
            rows = [a for a, _, _ in self._edges]
            cols = [b for _, b, _ in self._edges]
            n = self.grid.nx * self.grid.ny
            self._matrices[key] = coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
        return self._matrices[key]

    def _tree(self, start: int, height: float, t_s: float) -> np.ndarray:
        step = int(t_s // self.s.time_step_s)
        key = (height, step, start)
        if key not in self._trees:
            matrix = self._matrix(height, step)
            _, pred = dijkstra(matrix, directed=False, indices=start, return_predecessors=True)
            self._trees[key] = pred
        return self._trees[key]

    def path(self, a: Point, b: Point, height: float, t_s: float) -> list[Point]:
        """The cheapest path from a to b (the exact ends, the grid between); straight without a network."""
        if self.conn is None:
            return [a, b]
        start, goal = self.grid.node(a), self.grid.node(b)
        pred = self._tree(start, height, t_s)
        nodes = [goal]
        while nodes[-1] != start and pred[nodes[-1]] >= 0:
            nodes.append(int(pred[nodes[-1]]))
        middle = [self.grid.point(n) for n in reversed(nodes)][1:-1]
        return [a, *middle, b]

    def nc_length(self, path: Sequence[Point], height: float, t_s: float) -> float:
        """Metres of the path through cells predicted NC (sampled every half grid step)."""
        if self.conn is None:
            return 0.0
        bad = 0.0
        step = self.s.grid_m / 2
        for p, q in itertools.pairwise(path):
            length = math.dist(p, q)
            n = max(1, math.ceil(length / step))
            for k in range(n):
                f = (k + 0.5) / n
                x, y = p[0] + f * (q[0] - p[0]), p[1] + f * (q[1] - p[1])
                bad += length / n * (self.level((x, y), height, t_s) == "NC")
        return bad


def _length(path: Sequence[Point]) -> float:
    return sum(math.dist(p, q) for p, q in itertools.pairwise(path))


# ---- the plan --------------------------------------------------------------------------------------------


def plan(
    tasks: Sequence[Task],
    drones: Sequence[PlanDrone],
    conn: Connectivity | None,
    settings: PlanSettings,
    *,
    blind: bool = False,
) -> Plan:
    """The fleet's plan: `blind` ignores the network (and `conn`), as a fleet that has no prediction."""
    if not drones:
        raise ValueError("a plan needs at least one drone")
    ids = [t.id for t in tasks]
    if len(set(ids)) != len(ids):
        raise ValueError("task ids must be unique")
    router = Router(None if blind else conn, settings)
    heights = {t.id: settings.heights_m[0] if blind else _best_height(router, t.points_m[0]) for t in tasks}
    if blind:
        assignment = _greedy(tasks, drones, router)
    else:
        assignment = _improve(_assign(tasks, drones, router, heights), tasks, drones, router, heights)
    out = Plan()
    for drone in drones:
        out.legs[drone.id] = _legs_of(drone, assignment, tasks, router, heights, blind)
    if not blind:
        _book(out, {t.id: t for t in tasks}, settings)
    return out


def _best_height(router: Router, site: Point, t_s: float = 0.0) -> float:
    heights = router.s.heights_m
    return min(heights, key=lambda h: (RANK.get(router.level(site, h, t_s), 2), heights.index(h)))


def _task_s(task: Task, speed: float) -> float:
    return task.duration_s + (_length(task.points_m) / speed if task.kind == "route" else 0.0)


def _greedy(tasks: Sequence[Task], drones: Sequence[PlanDrone], router: Router) -> dict[str, str]:
    """Each task, in the order given, to the drone that can start it soonest (straight legs)."""
    free = {d.id: (0.0, d.start_m) for d in drones}
    speed = {d.id: d.speed_mps for d in drones}
    out = {}
    for task in tasks:
        site = task.points_m[0]
        best = min(free, key=lambda d: (free[d][0] + math.dist(free[d][1], site) / speed[d], d))
        t, at = free[best]
        out[task.id] = best
        free[best] = (t + math.dist(at, site) / speed[best] + _task_s(task, speed[best]), task.points_m[-1])
    return out


def _assign(
    tasks: Sequence[Task], drones: Sequence[PlanDrone], router: Router, heights: dict[str, float]
) -> dict[str, str]:
    """Minimise the makespan (each drone's tasks priced from its start) plus the predicted time without
    connectivity: a MILP over x[d, t] in {0, 1} and the makespan M."""
    if not tasks:
        return {}
    n_d, n_t = len(drones), len(tasks)
    cost = np.zeros((n_d, n_t))
    for i, drone in enumerate(drones):
        for j, task in enumerate(tasks):
            h = heights[task.id]
            path = router.path(drone.start_m, task.points_m[0], h, 0.0)
            fly = _length(path) / drone.speed_mps
            bad = router.nc_length(path, h, 0.0) / drone.speed_mps + _nc_on_task(
                task, router, h, drone.speed_mps
            )
            cost[i, j] = fly + _task_s(task, drone.speed_mps) + router.s.bad_weight_s * bad
    n = n_d * n_t
    c = np.concatenate([cost.ravel() * 1e-3, [1.0]])  # the makespan first, the total as a tie-break
    once = np.zeros((n_t, n + 1))
    for j in range(n_t):
        once[j, [i * n_t + j for i in range(n_d)]] = 1.0
    load = np.zeros((n_d, n + 1))
    for i in range(n_d):
        load[i, i * n_t : (i + 1) * n_t] = cost[i]
        load[i, n] = -1.0
    result = milp(
        c,
        integrality=np.concatenate([np.ones(n), [0]]),
        bounds=Bounds(np.zeros(n + 1), np.concatenate([np.ones(n), [np.inf]])),
        constraints=[LinearConstraint(once, 1, 1), LinearConstraint(load, -np.inf, 0)],
        options={"time_limit": 10.0},
    )
    if result.x is None:
        raise RuntimeError(f"the assignment found no solution: {result.message}")
    x = np.round(result.x[:n]).reshape(n_d, n_t)
    return {task.id: drones[int(np.argmax(x[:, j]))].id for j, task in enumerate(tasks)}


def _legs_of(
    drone: PlanDrone,
    assignment: dict[str, str],
    tasks: Sequence[Task],
    router: Router,
    heights: dict[str, float],
    blind: bool = False,
) -> list[Leg]:
    mine = _nearest_first([t for t in tasks if assignment[t.id] == drone.id], drone.start_m)
    return _timeline(drone, mine, router, heights, blind)


def _score(legs: dict[str, list[Leg]], bad_weight_s: float) -> float:
    """The plan's objective as flown: the makespan plus the price of the predicted time without
    connectivity, every drone's time as a tie-break."""
    ends = [drone_legs[-1].end_s for drone_legs in legs.values() if drone_legs]
    nc = sum(leg.nc_s for drone_legs in legs.values() for leg in drone_legs)
    return max(ends, default=0.0) + bad_weight_s * nc + 1e-3 * sum(ends)


def _improve(
    assignment: dict[str, str],
    tasks: Sequence[Task],
    drones: Sequence[PlanDrone],
    router: Router,
    heights: dict[str, float],
) -> dict[str, str]:
    """Local search from the MILP's assignment on the objective of the timelines themselves (which the
    MILP prices only from each drone's start): move one task to another drone, or swap two drones'
    tasks, while that lowers it; first improvement, in a fixed order, so the same inputs give the same
    plan."""
    by_id = {d.id: d for d in drones}
    legs = {d.id: _legs_of(d, assignment, tasks, router, heights) for d in drones}
    best = _score(legs, router.s.bad_weight_s)
    for _ in range(IMPROVE_ROUNDS):
        for candidate in _neighbours(assignment, tasks, drones):
            changed = {d for t, d in candidate.items() if assignment[t] != d} | {
                assignment[t] for t, d in candidate.items() if assignment[t] != d
            }
            trial = legs | {d: _legs_of(by_id[d], candidate, tasks, router, heights) for d in changed}
            score = _score(trial, router.s.bad_weight_s)
            if score < best - 1e-6:
                assignment, legs, best = candidate, trial, score
                break
        else:
            break
    return assignment


def _neighbours(
    assignment: dict[str, str], tasks: Sequence[Task], drones: Sequence[PlanDrone]
) -> Iterator[dict[str, str]]:
    for task in tasks:
        for drone in drones:
            if drone.id != assignment[task.id]:
                yield assignment | {task.id: drone.id}
    for a, b in itertools.combinations(tasks, 2):
        if assignment[a.id] != assignment[b.id]:
            yield assignment | {a.id: assignment[b.id], b.id: assignment[a.id]}


def _nc_on_task(task: Task, router: Router, height: float, speed: float, t_s: float = 0.0) -> float:
    if task.kind == "route":
        return router.nc_length(task.points_m, height, t_s) / speed
    return task.duration_s if router.level(task.points_m[0], height, t_s) == "NC" else 0.0


def _nearest_first(tasks: list[Task], start: Point) -> list[Task]:
    out, at, left = [], start, list(tasks)
    while left:
        nxt = min(left, key=lambda t: (math.dist(at, t.points_m[0]), t.id))
        left.remove(nxt)
        out.append(nxt)
        at = nxt.points_m[-1]
    return out


def _timeline(
    drone: PlanDrone, tasks: list[Task], router: Router, heights: dict[str, float], blind: bool
) -> list[Leg]:
    legs: list[Leg] = []
    t, at, h_at = 0.0, drone.start_m, router.s.heights_m[0]
    v = drone.speed_mps
    for task in tasks:
        h = heights[task.id]
        site = task.points_m[0]
        options = [h_at] if blind else sorted({h_at, h, *router.s.heights_m})  # transit at any height
        best = None
        for fly_h in options:
            path = router.path(at, site, fly_h, t)
            points = _flight(path, h_at, fly_h, h)
            key = (router.nc_length(path, fly_h, t), _length3(points))
            if best is None or key < best[0]:
                best = (key, points)
        assert best is not None
        (bad_m, metres), points = best
        legs.append(Leg("fly", t, t + metres / v, tuple(points), task.id, bad_m / v))
        t += metres / v
        on = _task_s(task, v)
        task_path = tuple((x, y, h) for x, y in task.points_m)
        legs.append(Leg("task", t, t + on, task_path, task.id, _nc_on_task(task, router, h, v, t)))
        t, at, h_at = t + on, task.points_m[-1], h
    return legs


def _flight(path: list[Point], h_from: float, fly_h: float, h_to: float) -> list[tuple[float, float, float]]:
    """The leg in 3D: climbing (or descending) to the transit height along its first stretch and to the
    task's height along its last, not on the spot; a straight leg that changes height on the way turns
    at its middle."""
    (ax, ay), (bx, by) = path[0], path[-1]
    middle = [(x, y, fly_h) for x, y in path[1:-1]]
    if not middle and fly_h not in (h_from, h_to):
        middle = [((ax + bx) / 2, (ay + by) / 2, fly_h)]
    return [(ax, ay, h_from), *middle, (bx, by, h_to)]


def _length3(points: Sequence[tuple[float, float, float]]) -> float:
    return sum(math.dist(p, q) for p, q in itertools.pairwise(points))


def _book(out: Plan, tasks: dict[str, Task], settings: PlanSettings) -> None:
    """Book each high-risk inspection's window, earliest first, within the budget of windows at once."""
    windows = sorted(
        (leg.start_s, leg.end_s, drone, leg.task)
        for drone, legs in out.legs.items()
        for leg in legs
        if leg.kind == "task" and tasks[leg.task].risk == "high" and tasks[leg.task].kind == "inspect"
    )
    for start, end, drone, task in windows:
        at_once = sum(1 for b in out.bookings if b.start_s < end and start < b.start_s + b.duration_s)
        if at_once >= settings.max_bookings:
            out.unbooked.append(task)
            continue
        out.bookings.append(
            BookingPlan(drone, task, start, end - start, tasks[task].points_m[0], settings.booking_radius_m)
        )
