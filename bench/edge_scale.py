"""Benchmark: does the edge grow with its MPC processes? The largest fleet M processes serve at 20 Hz,
as replicas (primary + standby per drone, edge/replicas.py) and as static shards, against one process.

A router, M real `dynqos edge mpc` processes and G load processes (each a zenoh session standing in for
its share of the fleet, as the drones' daemons do: a presence token per drone, its State every 50 ms on
the priority flow, express, reporting the term and replica it follows) all on this machine. A fleet of
D drones is served when at least 99% of its states are answered and the p99 state-to-command time is
under the 50 ms period. For each M and mode: the fleet sizes in turn up to the first not served, each
process's CPU (router, every MPC, every load process) as a share of a core per drone, and
`efficiency` = drones served with M processes / (M x drones served with one). Its smoke mode (CI, two
cores) flies one small fleet with one process and with two replicas; its full mode says how many cores
it had. The floor beside it: one process's CPU per drone at the same fleet (whatever the mode, each
drone's State must be decoded, solved and answered once).

Run: dynqos bench edge_scale (suite settings), or with its own options:
  python -m dynqos.bench.edge_scale [--processes 1,2] [--modes replicas,sharding] [--loaders 2]
      [--counts 25,50,75,100,125,150,175,200,250] [--seconds 3] [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import hovering_state, router_rig
from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus
from dynqos.experiment.processes import Processes, child_environment, cpu_s

PERIOD_S = 0.05
WARMUP_TICKS = 10  # before the measured span: the replicas settle who serves each drone
READY_TIMEOUT_S = 60.0  # a load process declares its drones and sees the MPC subscribe within this
MODES = ("replicas", "sharding")


# the load: one process per share of the fleet -----------------------------------------------------------
@dataclass
class Followed:
    """What a drone follows, as onboard/commands.py keeps it: the highest term seen and its replica."""

    term: int = 0
    replica: str = ""


def _drain(
    inbox: BoundedQueue[Received],
    sent: dict[tuple[str, int], float],
    followed: dict[str, Followed],
    latencies: list[float],
    until: float,
) -> None:
    """Commands until `until`: each first answer timed against its State, the highest term followed."""
    while (item := inbox.get(max(0.0, until - time.perf_counter()))) is not None:
        command = item.message
        if not isinstance(command, Command):
            continue
        seen = followed[command.uav]
        if command.term > seen.term or (command.term == seen.term and not seen.replica):
            seen.term, seen.replica = command.term, command.replica
        t_sent = sent.pop((command.uav, command.state_seq), None)
        if t_sent is not None:
            latencies.append(time.perf_counter() - t_sent)


def load(zcfg: ZenohConfig, first: int, count: int, ticks: int) -> dict[str, Any]:
    """Fly drones uav<first>.. as their daemons would: "ready" once the MPC follows each, then, after a
    "go" line on stdin, WARMUP_TICKS + `ticks` States each; the measured span's answers as JSON."""
    uavs = [f"uav{i}" for i in range(first, first + count)]
    with open_bus(zcfg, Role.DRONE) as bus:
        inbox: BoundedQueue[Received] = BoundedQueue(500_000)
        for uav in uavs:
            bus.subscribe(keys.downlink(uav, Downlink.COMMAND), inbox, expect=(Command,), direct=True)
        tokens = [bus.declare_token(keys.drone_presence(uav)) for uav in uavs]
        pubs = [
            bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True)
            for uav in uavs
        ]
        deadline = time.monotonic() + READY_TIMEOUT_S
        if not all(pub.wait_matched(max(0.1, deadline - time.monotonic())) for pub in pubs):
            raise SystemExit("edge_scale load: the MPC never followed every drone")
        print("ready", flush=True)
        if sys.stdin.readline().strip() != "go":
            raise SystemExit("edge_scale load: no go")
        followed = {uav: Followed() for uav in uavs}
        sent: dict[tuple[str, int], float] = {}
        latencies: list[float] = []
        seq_base = time.monotonic_ns() // 1_000_000  # rising across fleet sizes (the MPC keeps its seqs)
        cpu0, start = time.process_time(), time.perf_counter()
        for tick in range(WARMUP_TICKS + ticks):
            for i, (uav, pub) in enumerate(zip(uavs, pubs, strict=True)):
                seq = seq_base + tick + 1
                if tick >= WARMUP_TICKS:
                    sent[(uav, seq)] = time.perf_counter()
                seen = followed[uav]
                pub.put(hovering_state(uav, seq, i, seen.term, seen.replica))
            _drain(inbox, sent, followed, latencies, until=start + (tick + 1) * PERIOD_S)
        _drain(inbox, sent, followed, latencies, until=time.perf_counter() + 0.3)  # the last answers
        cpu = time.process_time() - cpu0
        del tokens
    return {"states": count * ticks, "latencies_ms": [round(s * 1000, 3) for s in latencies], "cpu_s": cpu}


# the sweep -----------------------------------------------------------------------------------------------
def _loaders(zcfg: ZenohConfig, drones: int, loaders: int, ticks: int) -> list[subprocess.Popen[str]]:
    shares = [drones // loaders + (1 if g < drones % loaders else 0) for g in range(loaders)]
    procs, first = [], 0
    for share in (s for s in shares if s):
        argv = [sys.executable, "-m", "dynqos.bench.edge_scale", "--load", f"{first},{share},{ticks}"]
        argv += ["--ports", f"{zcfg.default_port},{zcfg.priority_port}"]
        env = {**child_environment(os.environ), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        procs.append(
            subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
        )
        first += share
    return procs


def fleet(zcfg: ZenohConfig, procs: Processes, drones: int, loaders: int, seconds: float) -> dict[str, Any]:
    """One fleet size: every load process ready, then go; answers, latencies and each process's CPU."""
    ticks = round(seconds / PERIOD_S)
    load_procs = _loaders(zcfg, drones, loaders, ticks)
    try:
        for proc in load_procs:
            assert proc.stdout is not None
            if proc.stdout.readline().strip() != "ready":
                raise RuntimeError(f"a load process did not get ready (exit {proc.wait(10)})")
        edge = {name: p.pid for name, p in procs.procs.items()}
        before = {name: cpu_s(pid) or 0.0 for name, pid in edge.items()}
        t0 = time.perf_counter()
        for proc in load_procs:
            assert proc.stdin is not None
            proc.stdin.write("go\n")
            proc.stdin.flush()
        results = [json.loads(proc.communicate(timeout=seconds + 60)[0]) for proc in load_procs]
        span = time.perf_counter() - t0
        after = {name: cpu_s(pid) or 0.0 for name, pid in edge.items()}
        health = {name: _last_health(procs, name) for name in edge if name.startswith("mpc")}
    finally:
        for proc in load_procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
    latencies = sorted(ms for r in results for ms in r["latencies_ms"]) or [float("inf")]
    answered = len(latencies) / sum(r["states"] for r in results)
    p99 = latencies[min(len(latencies) - 1, int(0.99 * len(latencies)))]
    share = {name: (after[name] - before[name]) / span for name in edge}
    share.update({f"load{g}": r["cpu_s"] / span for g, r in enumerate(results)})
    return {
        "drones": drones,
        "answered": answered,
        "p50_ms": latencies[len(latencies) // 2],
        "p99_ms": p99,
        "served": answered >= 0.99 and p99 < PERIOD_S * 1000,
        "core_share": {k: round(v, 4) for k, v in share.items()},
        "mpc_core_share_per_drone": sum(v for k, v in share.items() if k.startswith("mpc")) / drones,
        "mpc_health": health,
    }


def _last_health(procs: Processes, name: str) -> dict[str, str]:
    """The MPC's newest health line as its fields (flying, standby, commands, solve times...)."""
    lines = [line for line in procs.tail(name, 400).split(" | ") if " replica=" in line]
    fields = (pair.split("=", 1) for pair in lines[-1].split() if "=" in pair) if lines else ()
    return {key: value for key, value in fields}


def sweep(mode: str, processes: int, counts: list[int], loaders: int, seconds: float) -> dict[str, Any]:
    extra = "[mpc]\nidle_timeout_s = 2\nhealth_interval_s = 1\n"
    if mode == "sharding":
        extra += f"shard_count = {processes}\n"
    rows = []
    with router_rig(extra) as (zcfg, procs):
        for index in range(processes):
            role = f"mpc.shard_index={index}" if mode == "sharding" else f"mpc.replica_id=mpc{index}"
            procs.start(f"mpc{index}", ["edge", "mpc", "--set", role])
        for count in counts:
            row = fleet(zcfg, procs, count, loaders, seconds)
            rows.append(row)
            print(
                f"edge_scale: {mode} x{processes}, {count} drones: answered {row['answered']:.2%}, "
                f"p99 {row['p99_ms']:.1f} ms, {'served' if row['served'] else 'not served'}",
                flush=True,
            )
            if not row["served"]:
                break
    served = max([r["drones"] for r in rows if r["served"]], default=0)
    return {"mode": mode, "processes": processes, "max_drones_at_20hz": served, "rows": rows}


def run(
    processes: list[int], modes: list[str], counts: list[int], loaders: int, seconds: float
) -> dict[str, Any]:
    one = sweep("one", 1, counts, loaders, seconds) if 1 in processes else None
    runs = [one] if one else []
    for m in (m for m in processes if m > 1):
        runs += [sweep(mode, m, counts, loaders, seconds) for mode in modes]
    base = one["max_drones_at_20hz"] if one else 0
    for r in runs:
        r["efficiency"] = r["max_drones_at_20hz"] / (r["processes"] * base) if base else None
        r["mpc_cpu_per_drone_over_one"] = _cpu_ratio(r, one)
    return {
        "benchmark": "edge_scale",
        **provenance(),
        "cores": os.cpu_count(),
        "loaders": loaders,
        "seconds_per_step": seconds,
        "runs": runs,
    }


def _cpu_ratio(run_: dict[str, Any], one: dict[str, Any] | None) -> float | None:
    """The MPC processes' CPU per drone over one process's, at the largest fleet both served."""
    if one is None:
        return None
    mine = {r["drones"]: r for r in run_["rows"] if r["served"]}
    theirs = {r["drones"]: r for r in one["rows"] if r["served"]}
    both = sorted(mine.keys() & theirs.keys())
    if not both:
        return None
    d = both[-1]
    return float(mine[d]["mpc_core_share_per_drone"] / theirs[d]["mpc_core_share_per_drone"])


def verdict(result: dict[str, Any]) -> str:
    runs = {(r["mode"], r["processes"]): r for r in result["runs"]}
    one = runs.get(("one", 1))
    two = runs.get(("replicas", 2))
    if one is None or two is None:
        return judged(False, "needs one process and two replicas in the sweep")
    ratio = two["mpc_cpu_per_drone_over_one"]
    met = two["max_drones_at_20hz"] >= one["max_drones_at_20hz"] and ratio is not None and ratio <= 1.3
    return judged(
        met,
        f"two replicas serve {two['max_drones_at_20hz']} drones, one process {one['max_drones_at_20hz']}; "
        f"their MPC CPU per drone {'-' if ratio is None else f'{ratio:.2f}x'} one's (target >= one's "
        f"drones, <= 1.3x; {result['cores']} cores)",
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| MPC processes | mode | drones | answered | p50 (ms) | p99 (ms) | served | MPC CPU per drone "
        "| router CPU per drone |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        for row in r["rows"]:
            rows.append(
                f"| {r['processes']} | {r['mode']} | {row['drones']} | {row['answered']:.2%} | "
                f"{row['p50_ms']:.1f} | {row['p99_ms']:.1f} | {'yes' if row['served'] else 'no'} | "
                f"{100 * row['mpc_core_share_per_drone']:.2f}% | "
                f"{100 * row['core_share']['router'] / row['drones']:.2f}% |"
            )
    rows += ["", "| MPC processes | mode | largest fleet served | efficiency | MPC CPU per drone / one's |"]
    rows.append("|---|---|---|---|---|")
    for r in result["runs"]:
        eff, ratio = r["efficiency"], r["mpc_cpu_per_drone_over_one"]
        rows.append(
            f"| {r['processes']} | {r['mode']} | {r['max_drones_at_20hz']} | "
            f"{'-' if eff is None else f'{eff:.2f}'} | {'-' if ratio is None else f'{ratio:.2f}x'} |"
        )
    return "\n".join(rows)


def _ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}") from None
    if not values or any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"expected whole numbers >= 1, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--processes", type=_ints, default=[1, 2], help="MPC process counts (default 1,2)")
    parser.add_argument("--modes", default="replicas,sharding", help="replicas, sharding or both (default)")
    parser.add_argument("--loaders", type=int, default=2, help="load processes (default 2)")
    parser.add_argument("--counts", type=_ints, help="fleet sizes in turn (default 25,50,75,...,200,250)")
    parser.add_argument("--seconds", type=float, default=3.0, help="measured per fleet size (default 3)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 10 drones, one and two replicas")
    parser.add_argument("--load", help=argparse.SUPPRESS)  # first,count,ticks: one load process
    parser.add_argument("--ports", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.load:
        first, count, ticks = (int(v) for v in args.load.split(","))
        default_port, priority_port = (int(v) for v in args.ports.split(","))
        zcfg = ZenohConfig(default_port=default_port, priority_port=priority_port)
        print(json.dumps(load(zcfg, first, count, ticks)), flush=True)
        return 0
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in MODES for m in modes):
        parser.error(f"--modes: choose from {', '.join(MODES)}")
    if not 1 <= args.loaders <= 64 or not 0.2 <= args.seconds <= 60:
        parser.error("--loaders must be in 1..64 and --seconds in 0.2..60")
    if args.quick:
        result = run([1, 2], ["replicas"], [10], 1, 1.0)
    else:
        counts = args.counts or [25, 50, 75, 100, 125, 150, 175, 200, 250]
        result = run(sorted(set(args.processes)), modes, counts, args.loaders, args.seconds)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
