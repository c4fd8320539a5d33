"""Four drones' camera parts into `dynqos edge detector` over a real router for 12 s; its CPU printed.

Each drone sends 15 frames a second of 4 rgb and 4 depth parts (1000 bytes each): 480 parts a second.
PACED=1: one part every 2 ms, as the onboard pacer spreads them; otherwise each frame's parts at once.
Run from the repository root with the project's venv at .venv: `python paced_parts.py CONFIG`.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from dynqos.common import keys
from dynqos.common.bus import Priority
from dynqos.common.config import load_config
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import CameraFrame
from dynqos.common.transport import Role, open_bus

DURATION_S = 12
FPS = 15
PARTS = 4  # per kind and frame


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().split()
    return (int(fields[13]) + int(fields[14])) / 100


def main(config: str, paced: bool) -> None:
    cfg = load_config(config)
    dynqos = ".venv/bin/dynqos"
    quiet = subprocess.DEVNULL
    router = subprocess.Popen([dynqos, "edge", "router", "--config", config], stderr=quiet)
    time.sleep(1.5)
    detector = subprocess.Popen([dynqos, "edge", "detector", "--config", config], stderr=quiet)
    time.sleep(3)
    bus = open_bus(cfg.zenoh, Role.DRONE)
    publishers = {}
    for n in range(1, 5):
        uav = f"uav{n}"
        bus.declare_token(keys.drone_presence(uav))
        publishers[uav] = {
            kind: bus.publisher(keys.uplink(uav, Flow.DEFAULT, stream), Priority.DATA)
            for kind, stream in (("rgb", Stream.CAMERA_RGB), ("depth", Stream.CAMERA_DEPTH))
        }
    start_cpu, start = cpu_s(detector.pid), time.monotonic()
    period = 1 / FPS
    due = start
    seq = 0
    while time.monotonic() - start < DURATION_S:
        seq += 1
        for uav, kinds in publishers.items():
            stamp = time.monotonic_ns()
            for kind, publisher in kinds.items():
                for part in range(PARTS):
                    publisher.put(
                        CameraFrame(
                            uav=uav,
                            seq=seq,
                            stamp_ns=stamp,
                            kind=kind,
                            encoding="jpeg" if kind == "rgb" else "zstd16",
                            width=104,
                            height=78,
                            intrinsics=(85.3, 85.3, 51.5, 38.5),
                            payload=b"\0" * 1000,
                            part=part,
                            parts=PARTS,
                            depth_unit_m=0.001,
                        )
                    )
                    if paced:
                        time.sleep(period / 32)
        due += period
        time.sleep(max(0.0, due - time.monotonic()))
    elapsed = time.monotonic() - start
    used = cpu_s(detector.pid) - start_cpu
    print(f"detector CPU {100 * used / elapsed:.1f}% of a core over {elapsed:.1f} s, {seq} frames per drone")
    for process in (detector, router):
        process.send_signal(signal.SIGTERM)
    for process in (detector, router):
        process.wait(10)
    bus.close()


if __name__ == "__main__":
    main(sys.argv[1], os.environ.get("PACED") == "1")
