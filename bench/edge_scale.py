"""Benchmark: does the edge grow with its MPC processes? The largest fleet M processes serve at 20 Hz,
as replicas (primary + standby per drone, edge/replicas.py) and as static shards, against one process.

A router, M real `dynqos edge mpc` processes and G load processes (each a zenoh session standing in for
its share of the fleet, as the drones' daemons do: a presence token per drone, its State every 50 ms on
the priority flow, express, reporting the term and replica it follows) all on this machine. A fleet of
D drones is served when at least 99% of its states are answered and the p99 state-to-command time is
under the 50 ms period, over a span that starts once the fleet settled (every drone appearing at once
is a cold start; each load process says how long it took, and per tick when the late and unanswered
states fell). For each M and mode: the fleet sizes in turn up to the first not served, each
process's CPU (router, every MPC, every load process) as a share of a core per drone, and
`efficiency` = drones served with M processes / (M x drones served with one). Its smoke mode (CI, two
cores) flies one small fleet with one process and with two replicas; its full mode says how many cores
it had, and `--per-process` scales the fleet sizes with M (for a host of many cores). The floor beside
it: one process's CPU per drone at the same fleet (whatever the mode, each drone's State must be
decoded, solved and answered once).

Run: dynqos bench edge_scale (suite settings), or with its own options:
  python -m dynqos.bench.edge_scale [--processes 1,2] [--modes replicas,sharding] [--loaders 2]
      [--counts 25,50,75,100,125,150,175,200,250] [--per-process] [--seconds 3] [--quick] [--out FILE]
      [--mpc-set mpc.standby_reads=copies ...]
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import IO, Any

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import hovering_state, router_rig
from dynqos.common import keys
from dynqos.common.config import ZenohConfig, load_config
from dynqos.common.errors import DynqosError
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus
from dynqos.experiment.machine import own_machine, usable_core_count
from dynqos.experiment.processes import Processes, child_environment, cpu_s

PERIOD_S = 0.05
# Before the measured span the fleet settles: every drone appearing at once is a cold start (each MPC
# subscribes, builds its controllers and takes its drones). The span starts once SETTLED_TICKS periods in
# a row had every State answered within the period, or after WARMUP_MAX_TICKS whatever happened; each
# load process says how long it took (`settle_s`).
SETTLED_TICKS = 5
WARMUP_MAX_TICKS = 200
READY_TIMEOUT_S = 60.0  # a load process declares its drones and sees the MPC subscribe within this
MODES = ("replicas", "sharding")


# the load: one process per share of the fleet -----------------------------------------------------------
@dataclass
class Followed:
    """What a drone follows, as onboard/commands.py keeps it: the highest term seen and its replica."""

    term: int = 0
    replica: str = ""


@dataclass
class Tally:
    """A load process's count of the answers: the States in flight ((uav, seq) -> when sent); during the
    warm-up, per seq how many were answered within the period; from `first_measured` on, every latency
    and the seqs of those answered late."""

    sent: dict[tuple[str, int], float] = field(default_factory=dict)
    prompt: Counter[int] = field(default_factory=Counter)
    first_measured: int | None = None
    latencies: list[float] = field(default_factory=list)
    late: list[int] = field(default_factory=list)


def _drain(inbox: BoundedQueue[Received], tally: Tally, followed: dict[str, Followed], until: float) -> None:
    """Commands until `until`: each first answer timed against its State, the highest term followed."""
    while (item := inbox.get(max(0.0, until - time.perf_counter()))) is not None:
        command = item.message
        if not isinstance(command, Command):
            continue
        seen = followed[command.uav]
        if command.term > seen.term or (command.term == seen.term and not seen.replica):
            seen.term, seen.replica = command.term, command.replica
        t_sent = tally.sent.pop((command.uav, command.state_seq), None)
        if t_sent is None:
            continue
        latency = time.perf_counter() - t_sent
        if tally.first_measured is None or command.state_seq < tally.first_measured:
            tally.prompt[command.state_seq] += latency <= PERIOD_S
            continue
        tally.latencies.append(latency)
        if latency > PERIOD_S:
            tally.late.append(command.state_seq)


def load(zcfg: ZenohConfig, first: int, count: int, ticks: int) -> dict[str, Any]:
    """Fly drones uav<first>.. as their daemons would: "ready" once the MPC follows each, then, after a
    "go" line on stdin, States every period: the warm-up until the fleet settled, then `ticks` measured;
    the measured span's answers as JSON."""
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
        tally = Tally()
        seq_base = time.monotonic_ns() // 1_000_000  # rising across fleet sizes (the MPC keeps its seqs)
        cpu0, start = time.process_time(), time.perf_counter()
        tick, settled_run = 0, 0
        measured_start = start
        # the warm-up until the fleet settled, then `ticks` measured from tally.first_measured on
        while tally.first_measured is None or seq_base + tick + 1 < tally.first_measured + ticks:
            seq = seq_base + tick + 1
            if tally.first_measured is None and (settled_run >= SETTLED_TICKS or tick >= WARMUP_MAX_TICKS):
                tally.first_measured = seq
                cpu0, measured_start = time.process_time(), time.perf_counter()
                print("measuring", flush=True)
            for i, (uav, pub) in enumerate(zip(uavs, pubs, strict=True)):
                tally.sent[(uav, seq)] = time.perf_counter()
                seen = followed[uav]
                pub.put(hovering_state(uav, seq, i, seen.term, seen.replica))
            _drain(inbox, tally, followed, until=start + (tick + 1) * PERIOD_S)
            if tally.first_measured is None and tick:  # the tick before: answers had two periods to come
                settled_run = settled_run + 1 if tally.prompt[seq - 1] == count else 0
            tick += 1
        cpu, measured_s = time.process_time() - cpu0, time.perf_counter() - measured_start
        print("done", flush=True)
        _drain(inbox, tally, followed, until=time.perf_counter() + 0.3)  # the last answers
        del tokens
    assert tally.first_measured is not None
    late_by_tick, missing_by_tick = [0] * ticks, [0] * ticks  # when in the span the misses fell
    for seq in tally.late:
        late_by_tick[seq - tally.first_measured] += 1
    for _, seq in tally.sent:  # unanswered
        if seq >= tally.first_measured:
            missing_by_tick[seq - tally.first_measured] += 1
    return {
        "states": count * ticks,
        "latencies_ms": [round(s * 1000, 3) for s in tally.latencies],
        "cpu_s": cpu,
        "measured_s": measured_s,
        "settle_s": round((tally.first_measured - seq_base - 1) * PERIOD_S, 2),
        "settled": settled_run >= SETTLED_TICKS,
        "late_by_tick": late_by_tick,
        "missing_by_tick": missing_by_tick,
    }


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
    lines = _Lines(load_procs)
    try:
        lines.until("ready", every=True, timeout_s=READY_TIMEOUT_S + 30)
        for proc in load_procs:
            assert proc.stdin is not None
            proc.stdin.write("go\n")
            proc.stdin.flush()
        # the edge's CPU from the last load process's first measured tick to the first one's last
        lines.until("measuring", every=True, timeout_s=WARMUP_MAX_TICKS * PERIOD_S + 30)
        # one that settled a whole span before another is done already: the CPU is read to the last
        overlap = not any(line == "done" for said in lines.said for line in said)
        edge = {name: p.pid for name, p in procs.procs.items()}
        before = {name: cpu_s(pid) or 0.0 for name, pid in edge.items()}
        t0 = time.perf_counter()
        lines.until("done", every=not overlap, timeout_s=seconds + 30)
        span = time.perf_counter() - t0
        after = {name: cpu_s(pid) or 0.0 for name, pid in edge.items()}
        health = {name: _last_health(procs, name) for name in edge if name.startswith("mpc")}
        lines.until("{", every=True, timeout_s=30)  # each one's result, a JSON line
        results = [json.loads(said[-1]) for said in lines.said]
    finally:
        for proc in load_procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait(5)
    latencies = sorted(ms for r in results for ms in r["latencies_ms"]) or [float("inf")]
    answered = len(latencies) / sum(r["states"] for r in results)
    p99 = latencies[min(len(latencies) - 1, int(0.99 * len(latencies)))]
    share = {name: (after[name] - before[name]) / span for name in edge}
    share.update({f"load{g}": r["cpu_s"] / r["measured_s"] for g, r in enumerate(results)})
    return {
        "drones": drones,
        "answered": answered,
        "p50_ms": latencies[len(latencies) // 2],
        "p99_ms": p99,
        "served": answered >= 0.99 and p99 < PERIOD_S * 1000,
        "core_share": {k: round(v, 4) for k, v in share.items()},
        "mpc_core_share_per_drone": sum(v for k, v in share.items() if k.startswith("mpc")) / drones,
        "settle_s": max(r["settle_s"] for r in results),
        "settled": all(r["settled"] for r in results),
        "spans_overlap": overlap,  # False: a load process's span ended before another's began
        "late_by_tick": [sum(at_tick) for at_tick in zip(*(r["late_by_tick"] for r in results), strict=True)],
        "missing_by_tick": [
            sum(at_tick) for at_tick in zip(*(r["missing_by_tick"] for r in results), strict=True)
        ],
        "mpc_health": health,
    }


class _Lines:
    """Each load process's stdout, read line by line on a thread of its own into one queue, so that
    every wait has its time-out and no read misses what another took ahead."""

    def __init__(self, load_procs: list[subprocess.Popen[str]]) -> None:
        self.said: list[list[str]] = [[] for _ in load_procs]
        self._queue: queue.Queue[tuple[int, str | None]] = queue.Queue()
        for index, proc in enumerate(load_procs):
            assert proc.stdout is not None
            threading.Thread(target=self._read, args=(index, proc.stdout), daemon=True).start()

    def _read(self, index: int, stream: IO[str]) -> None:
        for line in stream:
            self._queue.put((index, line.strip()))
        self._queue.put((index, None))  # its end

    def until(self, start: str, *, every: bool, timeout_s: float) -> None:
        """Until every load process (or, not `every`, one) has said a line starting with `start`."""
        deadline = time.monotonic() + timeout_s
        have = [any(line.startswith(start) for line in said) for said in self.said]
        while not (all(have) if every else any(have)):
            try:
                index, line = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"no load process said {start!r} within {timeout_s:.0f} s") from None
            if line is None and have[index]:  # it said it, then ended: its end is no news
                continue
            if line is None:
                last = self.said[index][-1][:80] if self.said[index] else "nothing"
                raise RuntimeError(f"load process {index} ended before it said {start!r} (last: {last!r})")
            self.said[index].append(line)
            have[index] = have[index] or line.startswith(start)


def _last_health(procs: Processes, name: str) -> dict[str, str]:
    """The MPC's newest health line as its fields (flying, standby, commands, solve times...)."""
    lines = [line for line in procs.tail(name, 400).split(" | ") if " replica=" in line]
    fields = (pair.split("=", 1) for pair in lines[-1].split() if "=" in pair) if lines else ()
    return {key: value for key, value in fields}


def sweep(
    mode: str, processes: int, counts: list[int], loaders: int, seconds: float, settings: tuple[str, ...] = ()
) -> dict[str, Any]:
    """`settings`: KEY=VALUE for every MPC process (`--mpc-set`)."""
    extra = "[mpc]\nidle_timeout_s = 2\nhealth_interval_s = 1\n"
    if mode == "sharding":
        extra += f"shard_count = {processes}\n"
    rows = []
    with router_rig(extra) as (zcfg, procs):
        for index in range(processes):
            role = f"mpc.shard_index={index}" if mode == "sharding" else f"mpc.replica_id=mpc{index}"
            procs.start(
                f"mpc{index}", ["edge", "mpc", "--set", role, *(a for kv in settings for a in ("--set", kv))]
            )
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
    processes: list[int],
    modes: list[str],
    counts: list[int],
    loaders: int,
    seconds: float,
    per_process: bool = False,
    settings: tuple[str, ...] = (),
) -> dict[str, Any]:
    """`per_process`: the counts are per MPC process, so M processes fly M x each (one sweep fits all M).
    `settings`: KEY=VALUE for every MPC process."""
    one = sweep("one", 1, counts, loaders, seconds, settings) if 1 in processes else None
    runs = [one] if one else []
    for m in (m for m in processes if m > 1):
        scaled = [c * m for c in counts] if per_process else counts
        runs += [sweep(mode, m, scaled, loaders, seconds, settings) for mode in modes]
    base = one["max_drones_at_20hz"] if one else 0
    for r in runs:
        r["efficiency"] = r["max_drones_at_20hz"] / (r["processes"] * base) if base else None
        r["mpc_cpu_per_drone_over_one"] = _cpu_ratio(r, one)
    return {
        "benchmark": "edge_scale",
        **provenance(),
        "cores": usable_core_count(),
        "cpu_quota_cores": None if (quota := own_machine()[1]) is None else quota.cores,
        "loaders": loaders,
        "seconds_per_step": seconds,
        "counts_per_process": per_process,
        "mpc_settings": list(settings),
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
    """Two replicas against one process (any host); eight replicas too where the sweep has them (a host
    of 16 cores or more: at least 6x one process's drones and at least 600)."""
    runs = {(r["mode"], r["processes"]): r for r in result["runs"]}
    one = runs.get(("one", 1))
    two = runs.get(("replicas", 2))
    eight = runs.get(("replicas", 8))
    if one is None or (two is None and eight is None):
        return judged(False, "needs one process and two or eight replicas in the sweep")
    base = one["max_drones_at_20hz"]
    met, said = True, []
    if two is not None:
        ratio = two["mpc_cpu_per_drone_over_one"]
        met = two["max_drones_at_20hz"] >= base and ratio is not None and ratio <= 1.3
        said.append(
            f"two replicas serve {two['max_drones_at_20hz']} drones, one process {base}; their MPC CPU per "
            f"drone {'-' if ratio is None else f'{ratio:.2f}x'} one's (target >= one's drones, <= 1.3x)"
        )
    if eight is not None:
        served = eight["max_drones_at_20hz"]
        met = met and served >= max(6 * base, 600)
        said.append(
            f"eight replicas serve {served} drones, {served / base if base else 0:.1f}x one's "
            "(target >= 6x and >= 600)"
        )
    return judged(met, "; ".join(said) + f"; {result['cores']} cores")


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
    parser.add_argument(
        "--per-process", action="store_true", help="the counts are per MPC process: M processes fly M x each"
    )
    parser.add_argument("--seconds", type=float, default=3.0, help="measured per fleet size (default 3)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 10 drones, one and two replicas")
    parser.add_argument(
        "--mpc-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a setting for every MPC process, e.g. mpc.standby_reads=copies (repeatable)",
    )
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
    settings = tuple(args.mpc_set)
    try:
        load_config(None, list(settings))  # a bad key or value is said before anything starts
    except DynqosError as exc:
        parser.error(f"--mpc-set: {exc}")
    if args.quick:
        result = run([1, 2], ["replicas"], [10], 1, 1.0, settings=settings)
    else:
        counts = args.counts or [25, 50, 75, 100, 125, 150, 175, 200, 250]
        processes = sorted(set(args.processes))
        result = run(processes, modes, counts, args.loaders, args.seconds, args.per_process, settings)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
