"""Benchmark: the onboard camera pipeline at 640x480 RGB-D: grab (the sim camera renders), encode
(JPEG q90 + zstd16 depth) and publish over a real zenoh link to a router, with the bitrate it produces.

CPU is process time per frame (all threads, zenoh's included) for each stage, of the drone's process
alone: the router and the edge's detector run as processes of their own (until 2026-12-07 they ran
inside the measured process, and their threads' CPU was counted as the drone's). Target: encode +
publish under 25% of one core at 30 fps; bitrate near the paper's ~47 Mbit/s.

Run: dynqos bench onboard_camera (suite settings), or with its own options:
  python -m dynqos.bench.onboard_camera [--frames 300] [--quick] [--out FILE]
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import router_rig
from dynqos.common import keys
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import CameraFrame
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus
from dynqos.onboard.camera import DEPTH_ENCODING, encode_depth, encode_rgb
from dynqos.sim.vehicle.camera import SimCamera
from dynqos.sim.vehicle.world import default_world


def _circling(t: float) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """The pose of a drone circling the arena's centre at 2 m, 1.5 m up, facing along its path, at `t`."""
    yaw = 0.5 * t + math.pi / 2
    return (2 * math.cos(0.5 * t), 2 * math.sin(0.5 * t), -1.5), (
        math.cos(yaw / 2),
        0.0,
        0.0,
        math.sin(yaw / 2),
    )


def run(frames: int) -> dict[str, Any]:
    """The drone's side alone in this process: the router and the edge (a real `dynqos edge detector`,
    which acks each frame as the daemon expects) run as processes of their own, as they do off the
    drone, so this process's CPU is what a companion computer pays for the camera."""
    with router_rig() as (zcfg, procs):
        procs.start("detector", ["edge", "detector"])
        drone = open_bus(zcfg, Role.DRONE)
        try:
            acks: BoundedQueue[Received] = BoundedQueue(100_000)
            drone.subscribe(keys.downlink("uav1", Downlink.CAMERA_ACK), acks)
            rgb_pub = drone.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
            depth_pub = drone.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_DEPTH), Priority.DATA)
            rgb_pub.wait_matched(10)
            depth_pub.wait_matched(10)
            camera = SimCamera(default_world(), 640, 480)
            grab_cpu = encode_cpu = publish_cpu = 0.0
            sent_bytes = 0
            wall0 = time.perf_counter()
            for i in range(frames):
                c0 = time.process_time()
                raw = camera.grab(_circling(i / 30))
                assert raw is not None
                assert raw.depth_m is not None
                c1 = time.process_time()
                jpeg, depth = encode_rgb(raw.rgb, 90), encode_depth(raw.depth_m)
                c2 = time.process_time()
                stamp = time.monotonic_ns()
                for pub, kind, encoding, payload in (
                    (rgb_pub, "rgb", "jpeg", jpeg),
                    (depth_pub, "depth", DEPTH_ENCODING, depth),
                ):
                    pub.put(
                        CameraFrame(
                            uav="uav1",
                            seq=i,
                            stamp_ns=stamp,
                            kind=kind,
                            encoding=encoding,
                            width=640,
                            height=480,
                            intrinsics=raw.intrinsics,
                            payload=payload,
                        )
                    )
                c3 = time.process_time()
                grab_cpu, encode_cpu, publish_cpu = (
                    grab_cpu + c1 - c0,
                    encode_cpu + c2 - c1,
                    publish_cpu + c3 - c2,
                )
                sent_bytes += len(jpeg) + len(depth)
            wall = time.perf_counter() - wall0
            got = 0
            deadline = time.monotonic() + 10
            while got < 2 * frames and time.monotonic() < deadline:
                if acks.get(0.5) is not None:
                    got += 1
        finally:
            drone.close()
    per_frame = {
        name: value / frames * 1000
        for name, value in (("grab_ms", grab_cpu), ("encode_ms", encode_cpu), ("publish_ms", publish_cpu))
    }
    return {
        "benchmark": "onboard_camera",
        **provenance(),
        "frames": frames,
        "cpu_ms_per_frame": per_frame,
        "encode_publish_core_share_at_30fps": (per_frame["encode_ms"] + per_frame["publish_ms"]) * 30 / 1000,
        "all_core_share_at_30fps": sum(per_frame.values()) * 30 / 1000,
        "mbps_at_30fps": sent_bytes * 8 / frames * 30 / 1e6,
        "max_fps_one_thread": frames / wall,
        "frames_delivered": got // 2,  # acked by the detector, both images
    }


def verdict(result: dict[str, Any]) -> str:
    share = result["encode_publish_core_share_at_30fps"]
    return judged(share <= 0.25, f"encode + publish at 30 fps take {share:.0%} of a core (target <= 25%)")


def markdown(result: dict[str, Any]) -> str:
    c = result["cpu_ms_per_frame"]
    return "\n".join(
        [
            "| stage (640x480 RGB-D) | CPU ms/frame | core share at 30 fps |",
            "|---|---|---|",
            f"| grab (sim render) | {c['grab_ms']:.1f} | {c['grab_ms'] * 0.03:.0%} |",
            f"| encode (JPEG q90 + zstd16) | {c['encode_ms']:.1f} | {c['encode_ms'] * 0.03:.0%} |",
            f"| publish (zenoh, to a router) | {c['publish_ms']:.1f} | {c['publish_ms'] * 0.03:.0%} |",
            "",
            f"encode + publish: {result['encode_publish_core_share_at_30fps']:.0%} of a core at 30 fps; "
            f"bitrate at 30 fps {result['mbps_at_30fps']:.1f} Mbit/s; "
            f"{result['frames_delivered']} of {result['frames']} frames delivered",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--frames", type=int, default=300, help="frames (default 300)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 10 frames")
    args = parser.parse_args(argv)
    if args.frames < 1:
        parser.error("--frames must be >= 1")
    result = run(10 if args.quick else args.frames)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
