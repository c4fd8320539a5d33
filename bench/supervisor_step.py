"""Benchmark: the cost of one supervisor step, beside its floor (the bare arithmetic of eq. 1-3).

Run: dynqos bench supervisor_step (suite settings), or with its own options:
  python -m dynqos.bench.supervisor_step [--steps N] [--quick] [--out FILE]
Target: median step under 50 microseconds.
"""

from __future__ import annotations

import math
import random
import sys
import time
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, micros, provenance
from dynqos.common.config import SupervisorConfig
from dynqos.onboard.supervisor import Inputs, Supervisor, sigmoid

TICK_NS = 50_000_000


def _inputs(n: int, seed: int = 0) -> list[Inputs]:
    rng = random.Random(seed)
    out = []
    for i in range(n):
        loaded = (i // 400) % 2 == 1  # alternate 20 s quiet / 20 s loaded at 20 Hz
        rtt = rng.gauss(90.0 if loaded else 20.0, 5.0)
        out.append(
            Inputs(
                cc_rtts_ms=[max(0.0, rtt)],
                camera_latencies_ms=[max(0.0, rng.gauss(150.0 if loaded else 40.0, 10.0))] if i % 2 else [],
                spaciousness_m=max(0.0, rng.gauss(4.0, 0.5)),
            )
        )
    return out


def _time_steps(inputs: list[Inputs]) -> list[int]:
    sup = Supervisor(SupervisorConfig())
    now = 0
    durations = []
    for item in inputs:
        now += TICK_NS
        start = time.perf_counter_ns()
        sup.step(item, now)
        durations.append(time.perf_counter_ns() - start)
    return durations


def _time_floor(inputs: list[Inputs]) -> list[int]:
    """Eq. 1-3 alone: two window means, three sigmoids, the weighted sum, the risk filter."""
    cfg = SupervisorConfig()
    cam: list[float] = []
    cc: list[float] = []
    s_k = 0.0
    durations = []
    for item in inputs:
        start = time.perf_counter_ns()
        cam = (cam + list(item.camera_latencies_ms))[-cfg.window[0] :]
        cc = (cc + list(item.cc_rtts_ms))[-cfg.window[1] :]
        t1 = math.fsum(cam) / len(cam) if cam else 0.0
        t2 = math.fsum(cc) / len(cc)
        p_lat = cfg.w[0] * sigmoid(t1, cfg.mu[0], cfg.rho[0]) + cfg.w[1] * sigmoid(t2, cfg.mu[1], cfg.rho[1])
        s_k = cfg.risk_a * s_k + cfg.risk_b * (item.spaciousness_m or 0.0)
        _ = (p_lat > cfg.th_lat, sigmoid(s_k, cfg.mu[2], cfg.rho[2]))
        durations.append(time.perf_counter_ns() - start)
    return durations


def run(steps: int) -> dict[str, Any]:
    inputs = _inputs(steps)
    _time_steps(inputs[: min(1000, steps)])  # warm up
    step = micros(_time_steps(inputs))
    floor = micros(_time_floor(inputs))
    return {
        "benchmark": "supervisor_step",
        **provenance(),
        "steps": steps,
        "step": step,
        "floor": floor,
        "ratio_median": step["median_us"] / floor["median_us"] if floor["median_us"] else math.inf,
        "target_median_us": 50.0,
    }


def verdict(result: dict[str, Any]) -> str:
    median = result["step"]["median_us"]
    target = result["target_median_us"]
    return judged(median < target, f"supervisor step median {median:.1f} us (target < {target:.0f} us)")


def markdown(result: dict[str, Any]) -> str:
    def row(name: str, figures: dict[str, float]) -> str:
        return f"| {name} | {figures['median_us']:.1f} | {figures['p99_us']:.1f} | {figures['mean_us']:.1f} |"

    return "\n".join(
        [
            "| what | median (us) | p99 (us) | mean (us) |",
            "|---|---|---|---|",
            row("supervisor step", result["step"]),
            row("floor: eq. 1-3 arithmetic only", result["floor"]),
            f"\nratio (median): {result['ratio_median']:.1f}x;"
            f" target: median under {result['target_median_us']:.0f} us",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument(
        "--steps", type=int, default=100_000, help="supervisor steps to time (default 100000)"
    )
    parser.add_argument("--quick", action="store_true", help="smoke mode: 2000 steps")
    args = parser.parse_args(argv)
    if args.steps < 10:
        parser.error("--steps must be at least 10")
    result = run(2000 if args.quick else args.steps)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
