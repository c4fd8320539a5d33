"""Benchmark: what the runtime adds to the control loop, beside bare zenoh in the same run.

Path measured: the drone's session (a peer with the two flow links, as the onboard daemon opens it)
publishes a State on the priority flow, handed over as the daemon's tick does it (to the uplink's queue,
put by its sender thread: onboard/uplink.py); the router forwards it to `dynqos edge mpc`, which solves
and answers with a Command; the drone wakes on it. Floor, on the very same session, links and router: a
bare zenoh-python responder (`bench/zenoh_echo.py`, its own process) answering a payload of the State's
size with one of the Command's size, same priority and express setting. The two alternate in blocks so
that drift in the machine's load hits both. The MPC's own time per answer is what it reports in each
Command (`edge_hold_ns`: arrival to publish). Target: our p50 within 1.5x of the floor's p50 plus the
MPC's p50. Then the same once more with a minimal Python MPC (`zenoh_echo --mpc`: decode, solve, answer,
and its own time in the Command) in the MPC's place: the ratio any Python MPC on zenoh gets here.

Run: dynqos bench control_loop (suite settings), or with its own options:
  python -m dynqos.bench.control_loop [--round-trips 2000] [--quick] [--out FILE]
"""

from __future__ import annotations

import queue
import statistics
import sys
import threading
import time
from typing import Any

import zenoh

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import router_rig
from dynqos.bench.zenoh_echo import PING, PONG
from dynqos.common import keys
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command, State, encode
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, ZenohBus, ZenohPublisher, open_bus
from dynqos.onboard.uplink import Uplink

UAV = "uav1"
BLOCK = 50
TIMEOUT_S = 5.0
PROBE_S = 0.5  # how long a readiness probe waits for its answer before the next probe


class NoAnswer(RuntimeError):
    """The MPC did not answer a state in time."""


def _state(seq: int) -> State:
    return State(
        uav=UAV,
        seq=seq,
        stamp_ns=time.monotonic_ns(),
        pos_m=(0.1, -0.2, -1.5),
        vel_mps=(0.0, 0.0, 0.0),
        quat=(1.0, 0.0, 0.0, 0.0),
        rtt_est_ms=0.0,
    )


def _summary(seconds: list[float]) -> dict[str, float]:
    ordered = sorted(seconds)
    return {
        "p50_ms": statistics.median(ordered) * 1000,
        "p99_ms": ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1000,
        "mean_ms": statistics.fmean(ordered) * 1000,
    }


class Loop:
    """Both round trips on one drone session."""

    def __init__(self, bus: ZenohBus) -> None:
        self.bus = bus
        self.presence = bus.declare_token(keys.drone_presence(UAV))  # as the drone's daemon does
        self.state_pub = bus.publisher(
            keys.uplink(UAV, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True
        )
        self.commands: BoundedQueue[Received] = BoundedQueue(64)
        bus.subscribe(keys.downlink(UAV, Downlink.COMMAND), self.commands)
        self.ping = bus.session.declare_publisher(PING, priority=zenoh.Priority.REAL_TIME, express=True)
        self.pongs: queue.SimpleQueue[int] = queue.SimpleQueue()
        self._pong_sub = bus.session.declare_subscriber(PONG, lambda _s: self.pongs.put(0))
        self.stop = threading.Event()
        self.uplink = Uplink(self.stop)
        self.uplink.start()
        self.seq = 0
        self.ping_bytes = len(encode(_state(1)))
        self.hold_ms: list[float] = []

    def wait_ready(self) -> None:
        self.wait_served()
        if not ZenohPublisher(self.ping, PING).wait_matched(30):  # zenoh's matching listener, no polling
            raise RuntimeError("the echo never subscribed to bench/ping")

    def wait_served(self, timeout_s: float = 30.0) -> None:
        """Until the MPC answers a state. A match on the state's key is not enough: it may be another
        subscriber of the states (a listener, a bridge) or an MPC that has just been stopped, and a
        state sent then is lost (the benchmark waited TIMEOUT_S for it and failed)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                self.ours(PROBE_S)
                return
            except NoAnswer:
                continue  # not following the drone yet: probe again
        raise RuntimeError(f"the MPC did not answer a state within {timeout_s:.0f} s")

    def ours(self, timeout_s: float = TIMEOUT_S) -> float:
        self.seq += 1
        start = time.perf_counter()
        self.uplink.put(Flow.PRIORITY, self.state_pub, _state(self.seq))
        while True:
            item = self.commands.get(max(0.0, start + timeout_s - time.perf_counter()))
            if item is None:
                raise NoAnswer(f"no Command for state {self.seq} within {timeout_s} s")
            command = item.message
            if isinstance(command, Command) and command.state_seq == self.seq:
                elapsed = time.perf_counter() - start
                self.hold_ms.append(command.edge_hold_ns / 1e6)
                return elapsed

    def bare(self) -> float:
        payload = bytes(self.ping_bytes)
        start = time.perf_counter()
        self.ping.put(payload)
        self.pongs.get(timeout=TIMEOUT_S)
        return time.perf_counter() - start


def run(round_trips: int) -> dict[str, Any]:
    with router_rig() as (zcfg, procs):
        procs.start("mpc", ["edge", "mpc"])
        command_bytes = len(encode(_sample_command()))
        procs.start(
            "echo",
            ["--reply-bytes", str(command_bytes)],
            program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"],
        )
        bus = open_bus(zcfg, Role.DRONE)
        try:
            loop = Loop(bus)
            loop.wait_ready()
            for _ in range(BLOCK):  # warm-up: routes, caches, the MPC's first solves
                loop.ours()
                loop.bare()
            ours, bare, hold = _blocks(loop, round_trips)
            # The same once more with a minimal Python MPC in the MPC's place: the floor of the ratio
            procs.stop("mpc")
            procs.start("minimal-mpc", ["--mpc"], program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"])
            loop.wait_served()
            _blocks(loop, BLOCK)  # warm-up
            minimal, minimal_bare, minimal_hold = _blocks(loop, round_trips)
            loop.stop.set()
            loop.uplink.join(timeout_s=5)
        finally:
            bus.close()
    ours_s, bare_s = _summary(ours), _summary(bare)
    mpc = _summary([ms / 1000 for ms in hold])
    minimal_mpc = _summary([ms / 1000 for ms in minimal_hold])
    minimal_s, minimal_bare_s = _summary(minimal), _summary(minimal_bare)
    return {
        "benchmark": "control_loop",
        **provenance(),
        "round_trips": len(ours),
        "state_bytes": loop.ping_bytes,
        "command_bytes": command_bytes,
        "ours": ours_s,
        "bare_zenoh": bare_s,
        "mpc_in_process": mpc,
        "ratio_p50": ours_s["p50_ms"] / (bare_s["p50_ms"] + mpc["p50_ms"]),
        "target_ratio": 1.5,
        "minimal_mpc": {
            "ours": minimal_s,
            "bare_zenoh": minimal_bare_s,
            "mpc_in_process": minimal_mpc,
            "ratio_p50": minimal_s["p50_ms"] / (minimal_bare_s["p50_ms"] + minimal_mpc["p50_ms"]),
        },
    }


def _blocks(loop: Loop, round_trips: int) -> tuple[list[float], list[float], list[float]]:
    """Our round trips and bare zenoh's, alternating in blocks (drift in the load hits both), and the
    MPC's own time for each of ours (ms)."""
    loop.hold_ms.clear()
    ours: list[float] = []
    bare: list[float] = []
    for block in range(max(1, round_trips // BLOCK)):
        order = (loop.ours, loop.bare) if block % 2 else (loop.bare, loop.ours)
        for measure in order:
            target = ours if measure == loop.ours else bare
            target.extend(measure() for _ in range(BLOCK))
    return ours, bare, list(loop.hold_ms)


def _sample_command() -> Command:
    return Command(
        uav=UAV,
        seq=1,
        state_seq=1,
        state_stamp_ns=1,
        edge_hold_ns=1,
        dt_s=0.05,
        accel_mps2=((0.123456789, -0.987654321, 0.5),) * 10,
        yaw_rad=(0.1,) * 10,
    )


def verdict(result: dict[str, Any]) -> str:
    ratio = result["ratio_p50"]
    return judged(
        ratio <= result["target_ratio"],
        f"state -> MPC -> command p50 {result['ours']['p50_ms']:.2f} ms is {ratio:.2f}x bare zenoh "
        f"({result['bare_zenoh']['p50_ms']:.2f} ms) + MPC ({result['mpc_in_process']['p50_ms']:.2f} ms) "
        "(target <= 1.5x)",
    )


def markdown(result: dict[str, Any]) -> str:
    o, b, m = result["ours"], result["bare_zenoh"], result["mpc_in_process"]
    mn = result["minimal_mpc"]
    return "\n".join(
        [
            f"| round trip on loopback via a router ({result['state_bytes']} B up, "
            f"{result['command_bytes']} B down) | p50 (ms) | p99 (ms) | mean (ms) |",
            "|---|---|---|---|",
            f"| dynqos: State -> edge MPC -> Command | {o['p50_ms']:.3f} | {o['p99_ms']:.3f} | "
            f"{o['mean_ms']:.3f} |",
            f"| floor: bare zenoh ping-pong, same sizes | {b['p50_ms']:.3f} | {b['p99_ms']:.3f} | "
            f"{b['mean_ms']:.3f} |",
            f"| MPC time inside the edge (arrival to publish) | {m['p50_ms']:.3f} | {m['p99_ms']:.3f} | - |",
            "",
            f"ratio (p50): {result['ratio_p50']:.2f}x of floor + MPC, {result['round_trips']} round trips",
            "",
            f"The same path with a minimal Python MPC (`zenoh_echo --mpc`) in the MPC's place: p50 "
            f"{mn['ours']['p50_ms']:.3f} ms against bare {mn['bare_zenoh']['p50_ms']:.3f} ms + its own "
            f"{mn['mpc_in_process']['p50_ms']:.3f} ms: {mn['ratio_p50']:.2f}x",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--round-trips", type=int, default=2000, help="per path (default 2000)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 100 round trips per path")
    args = parser.parse_args(argv)
    if args.round_trips < BLOCK:
        parser.error(f"--round-trips must be at least {BLOCK}")
    result = run(100 if args.quick else args.round_trips)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
