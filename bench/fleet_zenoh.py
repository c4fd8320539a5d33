"""Benchmark: how many drones one edge MPC process serves at 20 Hz over real zenoh, and at what CPU per
drone, beside the floor of any MPC process, on this machine.

A load client (one zenoh session standing in for the fleet) publishes a State for each of D drones
every 50 ms on the priority flow through a router to one process, and times each Command back. D is
served when at least 99% of the states are answered and the p99 state-to-command time is under the
50 ms period. Three processes take the MPC's place in turn, in the same run:
- `one_by_one`: `dynqos edge mpc` as before batching (`[mpc] batch_solves = false`, `batch_window_s =
  0`): one OSQP solve per State, each turn of its loop taking what arrived meanwhile;
- `batched`: `dynqos edge mpc` as shipped: the fresh States of a 2 ms window solved together
  (edge/mpc/batch.py);
- `floor`: a process that receives every State and answers it with a fixed Command, solving nothing
  (`zenoh_echo --fixed`): what receiving and answering alone cost on this stack.
Fleets grow in steps of 25 up to the first not served (and to 50 at least). Each size gives the
process's CPU per drone over the measured span (/proc/PID/stat). The load drones hover where they are,
so no bound of their QP binds (every State is solved by the batch; a flight's share is in docs/edge.md).
Targets (issue 72): the batched process serves at least 90% of the floor's fleet, and at 50 drones its
CPU per drone is at most 1.5x the floor's.

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
from dynqos.experiment.processes import cpu_s

PERIOD_S = 0.05
CPU_AT = 50  # the fleet at which the CPU per drone is compared


def _collect(
    commands: BoundedQueue[Received], sent: dict[tuple[str, int], float], latencies: list[float], until: float
) -> None:
    """Time each Command that arrives before `until` against the State it answers."""
    while (item := commands.get(max(0.0, until - time.perf_counter()))) is not None:
        if isinstance(item.message, Command):
            t_sent = sent.pop((item.message.uav, item.message.state_seq), None)
            if t_sent is not None:
                latencies.append(time.perf_counter() - t_sent)


def _load(zcfg: ZenohConfig, drones: int, seconds: float, pid: int) -> dict[str, Any]:
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
            raise RuntimeError("the MPC (or the floor) never subscribed")
        sent: dict[tuple[str, int], float] = {}
        latencies: list[float] = []
        ticks = round(seconds / PERIOD_S)
        warmup = 10
        # seq keeps rising across fleet sizes: the MPC still holds controllers from the previous size,
        # and a State whose seq is not above the last one it answered is (rightly) ignored as stale.
        seq_base = time.monotonic_ns() // 1_000_000
        start = time.perf_counter()
        cpu_from = cpu_to = 0.0
        for tick in range(warmup + ticks):
            if tick == warmup:
                cpu_from, measured_from = cpu_s(pid) or 0.0, time.perf_counter()
            for i, (uav, pub) in enumerate(pubs.items()):
                seq = seq_base + tick + 1
                if tick >= warmup:
                    sent[(uav, seq)] = time.perf_counter()
                pub.put(hovering_state(uav, seq, i))
            _collect(commands, sent, latencies, until=start + (tick + 1) * PERIOD_S)
        cpu_to, measured_to = cpu_s(pid) or 0.0, time.perf_counter()
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
        "core_share_per_drone": (cpu_to - cpu_from) / (measured_to - measured_from) / drones,
    }


PROCESSES = {  # what takes the MPC's place: its arguments, and its program (None: `dynqos`)
    "one_by_one": (["edge", "mpc", "--set", "mpc.batch_solves=false", "--set", "mpc.batch_window_s=0"], None),
    "batched": (["edge", "mpc", "--set", "mpc.batch_solves=true"], None),
    "floor": (["--fixed"], [sys.executable, "-m", "dynqos.bench.zenoh_echo"]),
}


def fleet(name: str, counts: list[int], seconds: float) -> dict[str, Any]:
    rows = []
    args, program = PROCESSES[name]
    with router_rig("[mpc]\nidle_timeout_s = 2\n") as (zcfg, procs):
        procs.start(name, args, program=program)
        pid = procs.procs[name].pid
        for count in counts:
            row = _load(zcfg, count, seconds, pid)
            rows.append(row)
            if not row["served"] and count >= CPU_AT:  # each process measured at CPU_AT drones at least
                break
    served = max([r["drones"] for r in rows if r["served"]], default=0)  # the largest served
    return {"process": name, "max_drones_at_20hz": served, "rows": rows}


def run(seconds: float, quick: bool) -> dict[str, Any]:
    counts = [10] if quick else list(range(25, 301, 25))
    result: dict[str, Any] = {"benchmark": "fleet_zenoh", **provenance(), "seconds_per_step": seconds}
    for name in PROCESSES:
        result[name] = fleet(name, counts, seconds)
    floor, batched = result["floor"], result["batched"]
    result["batched_over_floor_drones"] = batched["max_drones_at_20hz"] / max(1, floor["max_drones_at_20hz"])
    result["batched_over_floor_cpu_at_50"] = (
        _cpu_at(batched, CPU_AT) / _cpu_at(floor, CPU_AT) if not quick else None
    )
    return result


def _cpu_at(fleet: dict[str, Any], drones: int) -> float:
    return next((r["core_share_per_drone"] for r in fleet["rows"] if r["drones"] == drones), float("nan"))


def verdict(result: dict[str, Any]) -> str:
    drones = {name: result[name]["max_drones_at_20hz"] for name in PROCESSES}
    ratio, cpu = result["batched_over_floor_drones"], result["batched_over_floor_cpu_at_50"]
    cpu_text = "n/a" if cpu is None else f"{cpu:.2f}x"
    return judged(
        ratio >= 0.9 and cpu is not None and cpu <= 1.5,
        f"drones at 20 Hz: one by one {drones['one_by_one']}, batched {drones['batched']}, floor "
        f"{drones['floor']} ({ratio:.0%} of the floor's, target >= 90%); batched CPU per drone at 50 "
        f"drones {cpu_text} the floor's (target <= 1.5x)",
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| process | drones | answered | p50 (ms) | p99 (ms) | CPU per drone (% of a core) | served |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in PROCESSES:
        rows += [
            f"| {name} | {r['drones']} | {r['answered']:.1%} | {r['p50_ms']:.1f} | {r['p99_ms']:.1f} | "
            f"{r['core_share_per_drone']:.2%} | {'yes' if r['served'] else 'no'} |"
            for r in result[name]["rows"]
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
