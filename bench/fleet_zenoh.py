"""Benchmark: how many drones the edge MPC serves at 20 Hz over real zenoh, with one MPC process
and with two sharded by drone id (`[mpc] shard_count`), on this machine.

A load client (one zenoh session standing in for the fleet) publishes a State for each of D drones
every 50 ms on the priority flow through a router to the MPC process(es), and times each Command back.
D is served when at least 99% of the states are answered and the p99 state-to-command time is under
the 50 ms period. The in-process figure (no zenoh) is in `mpc_step`; this one adds the transport, the
router and the client, all sharing this machine's cores. Target: >= 100 drones per process.

Run: dynqos bench fleet_zenoh (suite settings), or with its own options:
  python -m dynqos.bench.fleet_zenoh [--seconds 3] [--quick] [--out FILE]
"""

from __future__ import annotations

import sys
import time
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import hovering_state, router_rig
from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus

PERIOD_S = 0.05


def _collect(
    commands: BoundedQueue[Received], sent: dict[tuple[str, int], float], latencies: list[float], until: float
) -> None:
    """Time each Command that arrives before `until` against the State it answers."""
    while (item := commands.get(max(0.0, until - time.perf_counter()))) is not None:
        if isinstance(item.message, Command):
            t_sent = sent.pop((item.message.uav, item.message.state_seq), None)
            if t_sent is not None:
                latencies.append(time.perf_counter() - t_sent)


def _load(zcfg: ZenohConfig, drones: int, seconds: float) -> dict[str, Any]:
    bus = open_bus(zcfg, Role.DRONE)
    try:
        commands: BoundedQueue[Received] = BoundedQueue(100_000)
        bus.subscribe(keys.downlink_all_drones(Downlink.COMMAND), commands)
        # each announced, as a drone's daemon does: the MPC follows these (held until the bus closes)
        tokens = [bus.declare_token(keys.drone_presence(f"uav{i}")) for i in range(drones)]
        pubs = {
            f"uav{i}": bus.publisher(
                keys.uplink(f"uav{i}", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True
            )
            for i in range(drones)
        }
        if not all(pub.wait_matched(30) for pub in pubs.values()):
            raise RuntimeError("the MPC never subscribed")
        sent: dict[tuple[str, int], float] = {}
        latencies: list[float] = []
        ticks = round(seconds / PERIOD_S)
        warmup = 10
        # seq keeps rising across fleet sizes: the MPC still holds controllers from the previous size,
        # and a State whose seq is not above the last one it answered is (rightly) ignored as stale.
        seq_base = time.monotonic_ns() // 1_000_000
        start = time.perf_counter()
        for tick in range(warmup + ticks):
            for i, (uav, pub) in enumerate(pubs.items()):
                seq = seq_base + tick + 1
                if tick >= warmup:
                    sent[(uav, seq)] = time.perf_counter()
                pub.put(hovering_state(uav, seq, i))
            _collect(commands, sent, latencies, until=start + (tick + 1) * PERIOD_S)
        _collect(commands, sent, latencies, until=time.perf_counter() + 0.2)  # the last tick's answers
        del tokens  # the drones leave (the MPC stops following them)
    finally:
        bus.close()
    states = drones * ticks
    ordered = sorted(latencies) or [float("inf")]
    answered = len(latencies) / states
    p99 = ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1000
    return {
        "drones": drones,
        "answered": answered,
        "p50_ms": ordered[len(ordered) // 2] * 1000,
        "p99_ms": p99,
        "served": answered >= 0.99 and p99 < PERIOD_S * 1000,
    }


def fleet(processes: int, counts: list[int], seconds: float) -> dict[str, Any]:
    rows = []
    with router_rig(f"[mpc]\nshard_count = {processes}\nidle_timeout_s = 2\n") as (zcfg, procs):
        for index in range(processes):
            procs.start(f"mpc{index}", ["edge", "mpc", "--set", f"mpc.shard_index={index}"])
        for count in counts:
            row = _load(zcfg, count, seconds)
            rows.append(row)
            if not row["served"]:
                break
    served = max([r["drones"] for r in rows if r["served"]], default=0)
    return {"processes": processes, "max_drones_at_20hz": served, "rows": rows}


def run(seconds: float, quick: bool) -> dict[str, Any]:
    counts = [10] if quick else [25, 50, 100, 150, 200, 300]
    return {
        "benchmark": "fleet_zenoh",
        **provenance(),
        "seconds_per_step": seconds,
        "one_process": fleet(1, counts, seconds),
        "two_processes": fleet(2, counts, seconds),
    }


def verdict(result: dict[str, Any]) -> str:
    one, two = result["one_process"]["max_drones_at_20hz"], result["two_processes"]["max_drones_at_20hz"]
    return judged(
        one >= 100, f"{one} drones at 20 Hz with one MPC process, {two} with two (target >= 100 per process)"
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| MPC processes | drones | answered | p50 (ms) | p99 (ms) | served |",
        "|---|---|---|---|---|---|",
    ]
    for key in ("one_process", "two_processes"):
        f = result[key]
        rows += [
            f"| {f['processes']} | {r['drones']} | {r['answered']:.1%} | {r['p50_ms']:.1f} | "
            f"{r['p99_ms']:.1f} | {'yes' if r['served'] else 'no'} |"
            for r in f["rows"]
        ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=3.0, help="measured per fleet size (default 3)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 10 drones for 0.5 s")
    args = parser.parse_args(argv)
    if not 0.2 <= args.seconds <= 60:
        parser.error("--seconds must be in 0.2..60")
    result = run(0.5 if args.quick else args.seconds, args.quick)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
