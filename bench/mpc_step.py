"""Benchmark: the MPC step, beside a bare OSQP solve of the same QP and a cvxpy (DPP) formulation,
and how many drones one MPC process serves at 20 Hz.

- step: `DroneController.step` for a State on a 2 m circle (reference handling, delay compensation,
  warm-started OSQP solve, building the horizon), at N = 20 and 40;
- floor: `osqp.OSQP.update` + `solve` with the vectors precomputed (what OSQP alone costs);
- cvxpy: the same QP with the initial state and reference as parameters (DPP), solved with OSQP;
- fleet: K controllers stepped every 50 ms in one process; the largest K whose p99 step stays under
  5 ms and whose whole round fits in the 50 ms period. Targets: step within 1.5x of bare OSQP,
  more than 10x faster than cvxpy, >= 100 drones per process.

Run: dynqos bench mpc_step (suite settings), or with its own options:
  python -m dynqos.bench.mpc_step [--steps 2000] [--quick] [--out FILE]
"""

from __future__ import annotations

import importlib
import math
import statistics
import sys
import time
from typing import Any

import numpy as np

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.common.config import ControlConfig, MpcConfig
from dynqos.common.messages import Reference, State
from dynqos.edge.mpc.controller import DroneController
from dynqos.edge.mpc.problem import MpcProblem
from dynqos.edge.planner.missions import Mission

DT_NS = 50_000_000
MISSION = Mission(kind="circle", lead_in_s=0.0)


def _state(uav: str, k: int, phase: float = 0.0) -> State:
    t = k * 0.05
    w = 2 * math.pi / 10
    return State(
        uav=uav,
        seq=k + 1,
        stamp_ns=(k + 1) * DT_NS,
        pos_m=(2 * math.cos(w * t + phase) + 0.05, 2 * math.sin(w * t + phase), -1.5),
        vel_mps=(-2 * w * math.sin(w * t + phase), 2 * w * math.cos(w * t + phase), 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        rtt_est_ms=30.0,
    )


def _controller(uav: str, horizon: int) -> DroneController:
    ctrl = DroneController(uav, MpcConfig(), ControlConfig(horizon=horizon))
    pos, vel, yaw = MISSION.samples(0.0, 0.05, 400)
    ctrl.reference.update(
        Reference(uav=uav, seq=1, stamp_ns=0, dt_s=0.05, pos_m=pos, vel_mps=vel, yaw_rad=yaw), 0
    )
    return ctrl


def _summary(seconds: list[float]) -> dict[str, float]:
    ordered = sorted(seconds)
    return {
        "median_ms": statistics.median(ordered) * 1000,
        "p99_ms": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1000,
    }


def step_vs_floor(horizon: int, steps: int) -> dict[str, Any]:
    """Our step and, interleaved, a second OSQP instance of the same QP fed the very vectors our step
    solved, in the same order (so both are warm-started alike and take the same iterations): the
    difference is what our code adds around the solver."""
    ctrl = _controller("uav1", horizon)
    bare = MpcProblem(MpcConfig(), ControlConfig(horizon=horizon))
    solved: list[tuple[Any, Any]] = []
    solve = ctrl.problem.solve

    def recording_solve(x0: Any, reference: Any) -> Any:
        solved.append((x0.copy(), reference.copy()))
        return solve(x0, reference)

    ctrl.problem.solve = recording_solve  # type: ignore[method-assign]
    ours, floor = [], []
    for k in range(steps):
        state = _state("uav1", k)
        start = time.perf_counter()
        ctrl.step(state, state.stamp_ns)
        ours.append(time.perf_counter() - start)
        q, lower, upper = bare.vectors(*solved.pop())
        start = time.perf_counter()
        bare.solver.update(q=q, l=lower, u=upper)
        bare.solver.solve(raise_error=False)
        floor.append(time.perf_counter() - start)
    result: dict[str, Any] = {
        "horizon": horizon,
        "step": _summary(ours[10:]),
        "bare_osqp": _summary(floor[10:]),
    }
    result["ratio_median"] = result["step"]["median_ms"] / result["bare_osqp"]["median_ms"]
    return result


def cvxpy_step(horizon: int, steps: int) -> dict[str, float] | None:
    try:
        cp: Any = importlib.import_module("cvxpy")  # optional: only this comparison needs it
    except ImportError:
        return None
    s = MpcConfig()
    ctrl = _controller("uav1", horizon)
    ad, bd = ctrl.problem.ad, ctrl.problem.bd
    q = np.diag([s.q_pos] * 3 + [s.q_vel] * 3)
    # DPP form: (x - r)' Q (x - r) = x' Q x - 2 (Q r)' x + const, with Q r as the parameter
    x0 = cp.Parameter(6)
    q_ref = cp.Parameter((horizon + 1, 6))
    x = cp.Variable((horizon + 1, 6))
    u = cp.Variable((horizon, 3))
    weights = np.sqrt(np.diag(q))
    cost = cp.sum_squares(cp.multiply(x[:horizon], weights)) + s.r_acc * cp.sum_squares(u)
    cost += s.terminal_factor * cp.sum_squares(cp.multiply(x[horizon], weights)) - 2 * cp.sum(
        cp.multiply(q_ref, x)
    )
    cons = [x[0] == x0] + [x[k + 1] == ad @ x[k] + bd @ u[k] for k in range(horizon)]
    cons += [cp.abs(x[:, 3:]) <= np.array(s.v_max_mps), cp.abs(u) <= np.array(s.a_max_mps2)]
    problem = cp.Problem(cp.Minimize(cost), cons)
    times = []
    for k in range(steps):
        state = _state("uav1", k)
        x0.value = np.array([*state.pos_m, *state.vel_mps])
        reference = ctrl.reference.window(state.stamp_ns, horizon + 1, 0.05)[0]  # type: ignore[index]
        q_ref.value = reference @ q * np.r_[np.ones(horizon), s.terminal_factor][:, None]
        start = time.perf_counter()
        problem.solve(
            solver=cp.OSQP,
            warm_start=True,
            canon_backend=cp.SCIPY_CANON_BACKEND,
            eps_abs=s.eps,
            eps_rel=s.eps,
            polishing=False,
            max_iter=s.max_iter,
        )
        times.append(time.perf_counter() - start)
    return _summary(times[2:])


def fleet(horizon: int, max_drones: int, rounds: int) -> dict[str, Any]:
    served = 0
    rows = []
    for count in (10, 25, 50, 100, 150, 200, 300, 400):
        if count > max_drones:
            break
        ctrls = [_controller(f"uav{i}", horizon) for i in range(count)]
        steps, round_ms = [], []
        for k in range(rounds):
            start_round = time.perf_counter()
            for i, ctrl in enumerate(ctrls):
                state = _state(ctrl.uav, k, phase=i * 0.1)
                start = time.perf_counter()
                ctrl.step(state, state.stamp_ns)
                steps.append(time.perf_counter() - start)
            round_ms.append((time.perf_counter() - start_round) * 1000)
        p99 = sorted(steps)[int(0.99 * len(steps))] * 1000
        worst_round = max(round_ms[2:])
        ok = p99 < 5.0 and worst_round < 50.0
        rows.append({"drones": count, "step_p99_ms": p99, "round_max_ms": worst_round, "ok": ok})
        if not ok:
            break
        served = count
    return {"horizon": horizon, "max_drones_at_20hz": served, "rows": rows}


def run(steps: int, quick: bool) -> dict[str, Any]:
    return {
        "benchmark": "mpc_step",
        **provenance(),
        "steps": [step_vs_floor(n, steps) for n in (20, 40)],
        "cvxpy": {str(n): cvxpy_step(n, 5 if quick else 60) for n in (20, 40)},
        "fleet": fleet(20, 10 if quick else 400, 5 if quick else 20),
    }


def verdict(result: dict[str, Any]) -> str:
    ratios = {s["horizon"]: s["ratio_median"] for s in result["steps"]}
    speedups = {
        s["horizon"]: result["cvxpy"][str(s["horizon"])]["median_ms"] / s["step"]["median_ms"]
        for s in result["steps"]
        if result["cvxpy"].get(str(s["horizon"]))
    }
    drones = result["fleet"]["max_drones_at_20hz"]
    met = all(r <= 1.5 for r in ratios.values()) and all(x > 10 for x in speedups.values()) and drones >= 100
    ratio_text = ", ".join(f"N={n} {r:.2f}x" for n, r in ratios.items())
    cvx_text = ", ".join(f"N={n} {x:.0f}x" for n, x in speedups.items()) or "cvxpy not installed"
    return judged(
        met,
        f"step vs bare OSQP {ratio_text} (<= 1.5x); faster than cvxpy {cvx_text} (> 10x); "
        f"{drones} drones per process at 20 Hz (>= 100)",
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| N | our step median / p99 (ms) | bare OSQP median / p99 (ms) | ratio | cvxpy DPP median (ms) |",
        "|---|---|---|---|---|",
    ]
    for entry in result["steps"]:
        cv = result["cvxpy"].get(str(entry["horizon"]))
        cv_text = f"{cv['median_ms']:.2f}" if cv else "-"
        rows.append(
            f"| {entry['horizon']} | {entry['step']['median_ms']:.3f} / {entry['step']['p99_ms']:.3f} | "
            f"{entry['bare_osqp']['median_ms']:.3f} / {entry['bare_osqp']['p99_ms']:.3f} | "
            f"{entry['ratio_median']:.2f}x | {cv_text} |"
        )
    f = result["fleet"]
    rows += [
        "",
        f"fleet (N = {f['horizon']}): {f['max_drones_at_20hz']} drones per process at 20 Hz",
        "",
        "| drones | step p99 (ms) | slowest round (ms) | within budget |",
        "|---|---|---|---|",
    ]
    rows += [
        f"| {r['drones']} | {r['step_p99_ms']:.2f} | {r['round_max_ms']:.1f} | {r['ok']} |" for r in f["rows"]
    ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--steps", type=int, default=2000, help="MPC steps per horizon (default 2000)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: few steps, small fleet")
    args = parser.parse_args(argv)
    if args.steps < 20:
        parser.error("--steps must be at least 20")
    result = run(40 if args.quick else args.steps, args.quick)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
