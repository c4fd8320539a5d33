"""Benchmark: the camera's delay-based rate controller's CPU per frame, beside its floor (aiortc's
estimator alone, fed the same parts: what any controller built on it spends), and the queue-delay
target's (`camera_rate_controller = "queue"`, onboard/queue_rate.py) on the same frames.

A frame is an RGB image in 12 parts and a depth image in 8, at 15 frames/s, over a link whose queue
grows and drains (so the estimator over-uses, decreases and ramps as in a flight). Per frame: the
camera thread's `sent` for both images, the two acks read (`acked`) and the factor asked once.

Run: dynqos bench camera_rate (suite settings), or with its own options:
  python -m dynqos.bench.camera_rate [--frames N] [--quick] [--out FILE]
Target: under 1% of a core at 15 frames/s (0.67 ms per frame).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, micros, provenance
from dynqos.onboard.camera_rate import DelayRateControl, PartSent, abs_send_time, new_estimator

FPS = 15.0
PARTS = {"rgb": 12, "depth": 8}
PART_BYTES = 4096
FRAME_NS = round(1e9 / FPS)
PART_GAP_NS = 600_000  # the pacing between parts


def _frames(count: int) -> list[list[tuple[str, list[PartSent], int, list[int]]]]:
    """Each frame's images: (kind, the parts sent, the first arrival, each part's arrival after it in us).
    The queue's delay swings between 5 and 200 ms over 8 s, so the detector sees over-use and recovery."""
    frames = []
    for seq in range(1, count + 1):
        t = seq * FRAME_NS
        images = []
        for kind, n in PARTS.items():
            parts = [PartSent(t + i * PART_GAP_NS, PART_BYTES) for i in range(n)]
            t += n * PART_GAP_NS
            arrivals = []
            for part in parts:
                phase = 2 * math.pi * part.sent_ns / 8e9
                arrivals.append(part.sent_ns + round((5 + 97.5 * (1 - math.cos(phase))) * 1e6))
            arrivals = [max(arrivals[: i + 1]) for i in range(len(arrivals))]  # a FIFO: never out of order
            images.append((kind, parts, arrivals[0], [(a - arrivals[0]) // 1000 for a in arrivals]))
        frames.append(images)
    return frames


def _time_controller(
    frames: list[list[tuple[str, list[PartSent], int, list[int]]]], controller: str = "gcc"
) -> list[int]:
    control = DelayRateControl(FPS, controller=controller)
    durations = []
    for seq, images in enumerate(frames, start=1):
        now = seq * FRAME_NS + 250_000_000
        start = time.perf_counter_ns()
        for kind, parts, _, _ in images:
            control.sent(seq, kind, parts)
        for kind, _, first, offsets in images:
            control.acked(seq, kind, first, offsets, now)
        control.factor(1.0, now)
        durations.append(time.perf_counter_ns() - start)
    return durations


def _time_floor(frames: list[list[tuple[str, list[PartSent], int, list[int]]]]) -> list[int]:
    estimator = new_estimator()
    durations = []
    for images in frames:
        start = time.perf_counter_ns()
        for _, parts, first, offsets in images:
            for part, offset in zip(parts, offsets, strict=True):
                estimator.add(
                    (first + offset * 1000) // 1_000_000, abs_send_time(part.sent_ns), part.nbytes, 0
                )
        durations.append(time.perf_counter_ns() - start)
    return durations


def _summary(durations: list[int]) -> dict[str, float]:
    figures = micros(durations)
    return {**figures, "core_share_at_15fps": figures["mean_us"] * FPS / 1e6}


def run(count: int) -> dict[str, Any]:
    frames = _frames(count)
    _time_controller(frames[: min(200, count)])  # warm up
    controller = _summary(_time_controller(frames))
    floor = _summary(_time_floor(frames))
    _time_controller(frames[: min(200, count)], "queue")
    queue = _summary(_time_controller(frames, "queue"))
    return {
        "benchmark": "camera_rate",
        **provenance(),
        "frames": count,
        "parts_per_frame": sum(PARTS.values()),
        "controller": controller,
        "floor": floor,
        "queue_controller": queue,
        "ratio_mean": controller["mean_us"] / floor["mean_us"] if floor["mean_us"] else math.inf,
        "target_core_share": 0.01,
    }


def verdict(result: dict[str, Any]) -> str:
    share = result["controller"]["core_share_at_15fps"]
    queue = result["queue_controller"]
    return judged(
        max(share, queue["core_share_at_15fps"]) < result["target_core_share"],
        f"rate controller {result['controller']['mean_us']:.0f} us per frame, {100 * share:.2f}% of a core "
        f"at 15 frames/s; the queue-delay target {queue['mean_us']:.0f} us, "
        f"{100 * queue['core_share_at_15fps']:.2f}% (target < {100 * result['target_core_share']:.0f}%)",
    )


def markdown(result: dict[str, Any]) -> str:
    def row(name: str, f: dict[str, float]) -> str:
        share = 100 * f["core_share_at_15fps"]
        return f"| {name} | {f['median_us']:.0f} | {f['p99_us']:.0f} | {f['mean_us']:.0f} | {share:.2f}% |"

    return "\n".join(
        [
            "| per frame (RGB 12 parts + depth 8) | median (us) | p99 (us) | mean (us) | core at 15 fps |",
            "|---|---|---|---|---|",
            row("the controller (sent, acked, factor)", result["controller"]),
            row("floor: aiortc's estimator alone", result["floor"]),
            row('the queue-delay target (controller = "queue")', result["queue_controller"]),
            f"\nratio (mean): {result['ratio_mean']:.2f}x; target: under "
            f"{100 * result['target_core_share']:.0f}% of a core at 15 frames/s",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--frames", type=int, default=20_000, help="frames to time (default 20000)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 1000 frames")
    args = parser.parse_args(argv)
    if args.frames < 10:
        parser.error("--frames must be at least 10")
    result = run(1000 if args.quick else args.frames)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
