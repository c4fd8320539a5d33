"""Benchmark: the simulator's speed in lock-step, and the camera's frame rate and CPU share.

- lock-step: simulated seconds per wall second of the vehicle model (200 Hz physics, RK4) flying a
  circle from offboard position setpoints at 50 Hz;
- camera: 640 x 480 RGB-D frames rendered from the default world along that circle (160 x 120 ray cast,
  upsampled, sensor noise), alone and with JPEG (quality 90) + PNG 16-bit depth encoding; CPU from
  process time. Floor: encoding an already rendered frame. Target: 30 fps within 25% of a core.

Run: dynqos bench vehicle_sim (suite settings), or with its own options:
  python -m dynqos.bench.vehicle_sim [--seconds 30] [--frames 300] [--quick] [--out FILE]
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import cv2
import numpy as np

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.model import VehicleModel
from dynqos.sim.vehicle.px4 import MAIN_OFFBOARD, Setpoint
from dynqos.sim.vehicle.render import Renderer
from dynqos.sim.vehicle.world import default_world


def circle(t: float) -> Setpoint:
    return Setpoint(pos_m=(2 * math.cos(0.5 * t), 2 * math.sin(0.5 * t), -1.5), yaw_rad=0.5 * t + math.pi / 2)


def lockstep(seconds: float) -> dict[str, float]:
    model = VehicleModel()
    model.fc.arm(True, model.state, True, 0)
    model.fc.on_setpoint(circle(0.0), 0)
    for _ in range(5):
        model.fc.on_setpoint(circle(0.0), model.now_ns)
        model.advance(0.02)
    model.fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns)
    start = time.perf_counter()
    for _ in range(round(seconds / 0.02)):
        model.fc.on_setpoint(circle(model.now_ns / 1e9), model.now_ns)
        model.advance(0.02)
    wall = time.perf_counter() - start
    return {"sim_seconds": seconds, "wall_seconds": wall, "sim_s_per_wall_s": seconds / wall}


def camera(frames: int) -> dict[str, Any]:
    renderer = Renderer(default_world())
    poses = []
    for i in range(frames):
        t = i / 30
        yaw = 0.5 * t + math.pi / 2
        poses.append(
            (
                np.array([2 * math.cos(0.5 * t), 2 * math.sin(0.5 * t), -1.5]),
                quat_to_rot(np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])),
            )
        )

    def run(encode: bool, render: bool) -> dict[str, float]:
        rgb, depth = renderer.render(*poses[0])
        sizes = []
        cpu0, wall0 = time.process_time(), time.perf_counter()
        for pos, rot in poses:
            if render:
                rgb, depth = renderer.render(pos, rot)
            if encode:
                _, jpg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 90])
                _, png = cv2.imencode(
                    ".png", (depth * 1000).astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1]
                )
                sizes.append(len(jpg) + len(png))
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
        out = {
            "fps": frames / wall,
            "cpu_ms_per_frame": cpu / frames * 1000,
            "core_share_at_30fps": cpu / frames * 30,
        }
        if sizes:
            out["mbps_at_30fps"] = float(np.mean(sizes)) * 8 * 30 / 1e6
        return out

    return {
        "render": run(False, True),
        "render_and_encode": run(True, True),
        "floor_encode_only": run(True, False),
    }


def run(seconds: float, frames: int) -> dict[str, Any]:
    return {
        "benchmark": "vehicle_sim",
        **provenance(),
        "lockstep": lockstep(seconds),
        "camera": camera(frames),
    }


def verdict(result: dict[str, Any]) -> str:
    speed = result["lockstep"]["sim_s_per_wall_s"]
    render = result["camera"]["render"]
    share = render["cpu_ms_per_frame"] * 30 / 1000
    return judged(
        speed > 1 and render["fps"] >= 30 and share <= 0.25,
        f"lock-step {speed:.1f}x real time; camera render {render['fps']:.0f} fps, {share:.0%} of a core "
        "at 30 fps (targets: faster than real time; 30 fps within 25% of one core)",
    )


def markdown(result: dict[str, Any]) -> str:
    lock, cam = result["lockstep"], result["camera"]
    rows = [
        f"lock-step: {lock['sim_s_per_wall_s']:.1f} simulated seconds per wall second"
        f" ({lock['sim_seconds']:.0f} s simulated)",
        "",
        "| camera 640x480 RGB-D | fps (one core) | CPU ms/frame | core share at 30 fps | Mbit/s at 30 fps |",
        "|---|---|---|---|---|",
    ]
    for name, key in (
        ("render", "render"),
        ("render + JPEG + PNG16", "render_and_encode"),
        ("floor: encode only", "floor_encode_only"),
    ):
        f = cam[key]
        mbps = f"{f['mbps_at_30fps']:.1f}" if "mbps_at_30fps" in f else "-"
        rows.append(
            f"| {name} | {f['fps']:.1f} | {f['cpu_ms_per_frame']:.1f} | {f['core_share_at_30fps']:.0%}"
            f" | {mbps} |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument(
        "--seconds", type=float, default=30.0, help="simulated seconds in lock-step (default 30)"
    )
    parser.add_argument("--frames", type=int, default=300, help="camera frames (default 300)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 2 s and 10 frames")
    args = parser.parse_args(argv)
    if args.seconds <= 0 or args.frames < 1:
        parser.error("--seconds must be > 0 and --frames >= 1")
    result = run(2.0, 10) if args.quick else run(args.seconds, args.frames)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
