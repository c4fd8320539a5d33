"""Benchmark: the CPU the cell emulator costs to forward real traffic, beside a bare asyncio relay.

Both run as their own process on 127.0.0.1 and forward the same paced load from a sender to a sink;
CPU time is read from /proc/<pid>/stat over the measured span. Target: under 50% of one
core at 100 Mbit/s.

Run: dynqos bench cell_forward (suite settings), or with its own options:
  python -m dynqos.bench.cell_forward [--mbps 100] [--seconds 5] [--quick] [--out FILE]
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from dynqos.bench.loadgen import Sink, send_paced
from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.experiment.processes import Processes

BARE_RELAY = r"""
import asyncio, sys
async def main(target_port):
    async def pipe(r, w):
        try:
            while data := await r.read(65536):
                w.write(data)
                await w.drain()
        finally:
            w.close()
    async def handle(r, w):
        ur, uw = await asyncio.open_connection("127.0.0.1", target_port)
        await asyncio.gather(pipe(r, uw), pipe(ur, w))
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    print(server.sockets[0].getsockname()[1], flush=True)
    await asyncio.sleep(3600)
asyncio.run(main(int(sys.argv[1])))
"""


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = int(fields[11]) + int(fields[12])  # utime + stime
    return ticks / os.sysconf("SC_CLK_TCK")


def measure(pid: int, port: int, sink: Sink, mbps: float, seconds: float) -> dict[str, float]:
    sender = threading.Thread(target=send_paced, args=(port, mbps * 1e6, seconds + 1.0, 64 * 1024))
    sender.start()
    threading.Event().wait(1.0)  # let the flow settle before measuring
    cpu0, t0 = cpu_seconds(pid), time.monotonic()
    threading.Event().wait(seconds)
    cpu1, t1 = cpu_seconds(pid), time.monotonic()
    sender.join(timeout=30)
    return {
        "cpu_share_of_one_core": (cpu1 - cpu0) / (t1 - t0),
        "delivered_mbps": sink.rate_mbps(t0, t1),
    }


def run(mbps: float, seconds: float) -> dict[str, Any]:
    sink = Sink()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            toml = f"""
[cell]
uplink_mbps = {mbps * 10}
downlink_mbps = {mbps * 10}
control_port = 0
jitter_ms = 0
[[cell.bearers]]
name = "drone"
target = "127.0.0.1:{sink.port}"
[[cell.background]]
name = "bg"
"""
            config = Path(tmp) / "cell.toml"
            config.write_text(toml)
            procs = Processes(config, Path(tmp))
            try:
                info = procs.start("cell", ["sim", "cell", "--duration", str(seconds + 30)])
                port = info["bearers"]["drone"]["port"]
                emulator = measure(procs.procs["cell"].pid, port, sink, mbps, seconds)
            finally:
                procs.stop_all()
        with subprocess.Popen(
            [sys.executable, "-c", BARE_RELAY, str(sink.port)], stdout=subprocess.PIPE, text=True
        ) as relay:
            try:
                assert relay.stdout is not None
                port = int(relay.stdout.readline())
                bare = measure(relay.pid, port, sink, mbps, seconds)
            finally:
                relay.terminate()  # our own child, by its pid
                relay.wait(timeout=10)
    finally:
        sink.close()
    return {
        "benchmark": "cell_forward",
        **provenance(),
        "offered_mbps": mbps,
        "seconds": seconds,
        "emulator": emulator,
        "bare_relay": bare,
        "target_cpu_share": 0.5,
    }


def verdict(result: dict[str, Any]) -> str:
    share = result["emulator"]["cpu_share_of_one_core"]
    offered, target = result["offered_mbps"], result["target_cpu_share"]
    return judged(
        share < target, f"cell emulator {share:.0%} of a core at {offered:.0f} Mbit/s (target < {target:.0%})"
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| what | CPU (share of one core) | delivered (Mbit/s) |",
        "|---|---|---|",
    ]
    for name, key in (
        ("cell emulator (1 ms TTI, scheduler, delay line)", "emulator"),
        ("floor: bare asyncio relay", "bare_relay"),
    ):
        figures = result[key]
        rows.append(f"| {name} | {figures['cpu_share_of_one_core']:.1%} | {figures['delivered_mbps']:.1f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--mbps", type=float, default=100.0, help="offered load (default 100)")
    parser.add_argument("--seconds", type=float, default=5.0, help="measured span (default 5)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 10 Mbit/s for 1 s")
    args = parser.parse_args(argv)
    if args.mbps <= 0 or args.seconds <= 0:
        parser.error("--mbps and --seconds must be > 0")
    result = run(10.0, 1.0) if args.quick else run(args.mbps, args.seconds)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
