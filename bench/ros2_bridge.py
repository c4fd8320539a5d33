"""Benchmark: what `dynqos edge ros2` costs (docs/ros2.md): its CPU per drone, the time it adds to a
drone's pose on its way to a ROS 2 node, and whether the control loop notices it running.

1. Pose latency. A drone session publishes a State on the priority flow; the bridge, publishing each
   message as it comes (`[ros2] publish_period_s = 0`: its work, not its pacing), publishes its pose
   (and odometry and /tf) in rmw_zenoh's format; a raw zenoh subscriber on the pose's data key, a ROS
   node's part, times it from the put (with the default period a pose waits up to that long more).
   The floor, on the same sessions and router: a bare zenoh-python responder (bench/zenoh_echo.py)
   answering a payload of the State's size with one of the pose's size. The two alternate in blocks
   of 50, one state at a time.
2. CPU per drone, the bridge as configured by default. D = 1, 2, 4, 8 drones' States at 20 Hz and
   SupervisorStatus at 5 Hz for `--seconds`, a ROS listener subscribed to every topic the bridge
   publishes (zenoh sends nothing to nobody), the bridge's CPU seconds (/proc/PID/stat); the cost per
   drone is the least-squares slope.
3. The control loop of `control_loop` (State -> `dynqos edge mpc` -> Command), paced at 100 Hz, with the
   bridge and its listener running, without, and with the floor of any watcher (a bare zenoh
   subscriber of the states: the router then sends each state twice), each once per round, four rounds,
   the order rotated: the bridge shares the router and the cores, never the loop's keys.
Target: the loop's p50 with the bridge on within 5% of the loop's p50 without it.

Run: dynqos bench ros2_bridge (suite settings), or with its own options:
  python -m dynqos.bench.ros2_bridge [--round-trips 1000] [--seconds 5] [--quick] [--out FILE]
"""

from __future__ import annotations

import contextlib
import queue
import statistics
import sys
import time
from collections.abc import Iterator
from typing import Any

import zenoh

from dynqos.bench.control_loop import BLOCK, TIMEOUT_S, UAV, Loop, _sample_command, _state, _summary
from dynqos.bench.edge_per_drone import _slope, _status
from dynqos.bench.observability import _paced
from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import router_rig
from dynqos.bench.zenoh_echo import PING, PONG
from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.errors import DynqosError
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import State, encode
from dynqos.common.transport import Priority, Role, ZenohBus, open_bus
from dynqos.experiment.processes import Processes, cpu_s

PREFIX = "dynqos"  # the bridge's default [ros2] prefix, domain 0
ROS_TOPICS = "0/dynqos/**"  # every data key the bridge publishes per drone ...
ROS_TF = "0/tf/**"  # ... and /tf
ROUNDS = 4
PERIOD_S = 0.05
DRONE_COUNTS = (1, 2, 4, 8)


def _ros2_codec() -> Any:
    try:
        from dynqos.edge.ros2 import codec, wire
    except ImportError as exc:  # rosbags: the ros2 extra
        raise DynqosError(f"ros2_bridge needs the ros2 extra: pip install 'dynqos[ros2]' ({exc})") from None
    return codec, wire


def _listener(procs: Processes, name: str) -> None:
    """A ROS 2 node's part in its own process: subscribed to every topic the bridge publishes."""
    for index, key in enumerate((ROS_TOPICS, ROS_TF)):
        procs.start(
            f"{name}-{index}", ["--listen", key], program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"]
        )


def _stop_listener(procs: Processes, name: str) -> None:
    for index in range(2):
        procs.stop(f"{name}-{index}")


def pose_latency(zcfg: ZenohConfig, procs: Processes, round_trips: int) -> dict[str, Any]:
    codec, wire = _ros2_codec()
    pose_bytes = len(codec.pose_stamped(time.time_ns(), "map", (0.1, -0.2, -1.5), (1.0, 0.0, 0.0, 0.0)))
    procs.start(
        "echo", ["--reply-bytes", str(pose_bytes)], program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"]
    )
    procs.start("ros2", ["edge", "ros2", "--set", "ros2.publish_period_s=0"])  # its work, not its period
    bus = open_bus(zcfg, Role.DRONE)
    try:
        poses: queue.SimpleQueue[int] = queue.SimpleQueue()
        pose_key = wire.topic_key(0, f"/{PREFIX}/{UAV}/pose", codec.POSE, codec.type_hash(codec.POSE))
        bus.session.declare_subscriber(pose_key, lambda _s: poses.put(0))
        state_pub = bus.publisher(
            keys.uplink(UAV, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True
        )
        ping = bus.session.declare_publisher(PING, priority=zenoh.Priority.REAL_TIME, express=True)
        pongs: queue.SimpleQueue[int] = queue.SimpleQueue()
        bus.session.declare_subscriber(PONG, lambda _s: pongs.put(0))
        if not state_pub.wait_matched(30):
            raise RuntimeError("the bridge never subscribed to the drone's state")
        state_bytes = len(encode(_state(1)))
        seq = 0

        def bridged() -> float:
            nonlocal seq
            seq += 1
            start = time.perf_counter()
            state_pub.put(_state(seq))
            poses.get(timeout=TIMEOUT_S)
            return time.perf_counter() - start

        def bare() -> float:
            start = time.perf_counter()
            ping.put(bytes(state_bytes))
            pongs.get(timeout=TIMEOUT_S)
            return time.perf_counter() - start

        bridged()  # the bridge declares the drone's topics on its first state
        for _ in range(BLOCK):
            bridged()
            bare()
        ours: list[float] = []
        floor: list[float] = []
        for block in range(max(1, round_trips // BLOCK)):
            for measure in (bridged, bare) if block % 2 else (bare, bridged):
                (ours if measure is bridged else floor).extend(measure() for _ in range(BLOCK))
    finally:
        bus.close()
        procs.stop("ros2")
        procs.stop("echo")
    bridged_s, bare_s = _summary(ours), _summary(floor)
    return {
        "round_trips": len(ours),
        "state_bytes": state_bytes,
        "pose_bytes": pose_bytes,
        "bridged": bridged_s,
        "bare_zenoh": bare_s,
        "added_p50_ms": bridged_s["p50_ms"] - bare_s["p50_ms"],
    }


def _drone_load(bus: ZenohBus, drones: int, seconds: float) -> None:
    """`drones` drones' States at 20 Hz and statuses at 5 Hz for `seconds` (paced, not synchronising)."""
    uavs = [f"uav{i}" for i in range(drones)]
    states = {
        u: bus.publisher(keys.uplink(u, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True)
        for u in uavs
    }
    statuses = {u: bus.publisher(keys.uplink(u, Flow.DEFAULT, Stream.STATUS), Priority.DATA) for u in uavs}
    ticks = round(seconds / PERIOD_S)
    start = time.perf_counter()
    for tick in range(ticks):
        for i, uav in enumerate(uavs):
            states[uav].put(
                State(
                    uav=uav,
                    seq=tick + 1,
                    stamp_ns=time.monotonic_ns(),
                    pos_m=(0.1 * i, 0.0, -1.5),
                    vel_mps=(0.5, 0.0, 0.0),
                    quat=(1.0, 0.0, 0.0, 0.0),
                )
            )
            if tick % 4 == 0:
                statuses[uav].put(_status(uav, tick + 1, time.monotonic_ns()))
        delay = start + (tick + 1) * PERIOD_S - time.perf_counter()
        if delay > 0:
            time.sleep(delay)  # the drones' rate, not synchronisation


def cpu_per_drone(zcfg: ZenohConfig, procs: Processes, seconds: float) -> dict[str, Any]:
    _ros2_codec()
    procs.start("ros2-cpu", ["edge", "ros2"])
    _listener(procs, "ros-node")
    pid = procs.procs["ros2-cpu"].pid
    rows = []
    bus = open_bus(zcfg, Role.DRONE)
    try:
        for drones in DRONE_COUNTS:
            _drone_load(bus, drones, 1.0)  # warm-up: the bridge declares each drone's topics
            before = cpu_s(pid) or 0.0
            _drone_load(bus, drones, seconds)
            used = (cpu_s(pid) or 0.0) - before
            rows.append({"drones": drones, "core_share": used / seconds})
    finally:
        bus.close()
        _stop_listener(procs, "ros-node")
        procs.stop("ros2-cpu")
    intercept, slope = _slope([r["drones"] for r in rows], [r["core_share"] for r in rows])
    return {"rows": rows, "per_drone_core_share": slope, "idle_core_share": intercept}


LOOP_MODES = ("off", "floor", "on")  # floor: a bare subscriber of the states, what any watcher costs


@contextlib.contextmanager
def _loop_phase(procs: Processes, index: int, mode: str) -> Iterator[None]:
    if mode == "on":
        procs.start(f"ros2-{index}", ["edge", "ros2"])
        _listener(procs, f"ros-{index}")
    elif mode == "floor":
        procs.start(
            f"states-{index}",
            ["--listen", keys.uplink_all_drones(Stream.STATE)],
            program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"],
        )
    try:
        yield
    finally:
        if mode == "on":
            _stop_listener(procs, f"ros-{index}")
            procs.stop(f"ros2-{index}")
        elif mode == "floor":
            procs.stop(f"states-{index}")


def control_loop(
    zcfg: ZenohConfig, procs: Processes, round_trips: int, rounds: int = ROUNDS
) -> dict[str, Any]:
    procs.start("mpc", ["edge", "mpc"])
    procs.start(
        "loop-echo",
        ["--reply-bytes", str(len(encode(_sample_command())))],
        program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"],
    )
    samples: dict[str, list[float]] = {mode: [] for mode in LOOP_MODES}
    phase_p50: dict[str, list[float]] = {mode: [] for mode in LOOP_MODES}
    per_phase = max(BLOCK, round_trips // rounds)
    order = [LOOP_MODES[(i + r) % len(LOOP_MODES)] for r in range(rounds) for i in range(len(LOOP_MODES))]
    bus = open_bus(zcfg, Role.DRONE)
    try:
        loop = Loop(bus)
        loop.wait_ready()
        for index, mode in enumerate(order):
            with _loop_phase(procs, index, mode):
                for _ in range(BLOCK):  # warm-up: the new routes
                    loop.ours()
                measured = _paced(loop, per_phase, 100.0)
            samples[mode].extend(measured)
            phase_p50[mode].append(statistics.median(measured) * 1000)
        loop.stop.set()
        loop.uplink.join(timeout_s=5)
    finally:
        bus.close()
        procs.stop("loop-echo")
        procs.stop("mpc")
    figures: dict[str, dict[str, Any]] = {
        mode: {**_summary(samples[mode]), "phase_p50_ms": phase_p50[mode]} for mode in LOOP_MODES
    }
    off = figures["off"]["p50_ms"]
    return {
        **figures,
        "change_p50": figures["on"]["p50_ms"] / off - 1,
        "floor_change_p50": figures["floor"]["p50_ms"] / off - 1,
    }


def run(round_trips: int, seconds: float, rounds: int = ROUNDS) -> dict[str, Any]:
    with router_rig() as (zcfg, procs):
        latency = pose_latency(zcfg, procs, round_trips)
        cpu = cpu_per_drone(zcfg, procs, seconds)
        loop = control_loop(zcfg, procs, round_trips, rounds)
    return {
        "benchmark": "ros2_bridge",
        **provenance(),
        "seconds_per_size": seconds,
        "pose_latency": latency,
        "cpu": cpu,
        "control_loop": loop,
        "target_change_p50": 0.05,
    }


def verdict(result: dict[str, Any]) -> str:
    loop, latency, cpu = result["control_loop"], result["pose_latency"], result["cpu"]
    return judged(
        loop["change_p50"] <= result["target_change_p50"],
        f"control loop p50 {loop['on']['p50_ms']:.2f} ms with the bridge on against "
        f"{loop['off']['p50_ms']:.2f} ms off ({loop['change_p50'] * 100:+.1f}%, target <= +5%; a bare "
        f"subscriber of the states: {loop['floor_change_p50'] * 100:+.1f}%); a pose reaches ROS "
        f"{latency['added_p50_ms']:.2f} ms after bare zenoh would; "
        f"{cpu['per_drone_core_share'] * 100:.2f}% of a core per drone",
    )


def markdown(result: dict[str, Any]) -> str:
    latency, cpu, loop = result["pose_latency"], result["cpu"], result["control_loop"]
    rows = [
        f"| pose to a ROS 2 subscriber ({latency['state_bytes']} B up, {latency['pose_bytes']} B down) "
        "| p50 (ms) | p99 (ms) | mean (ms) |",
        "|---|---|---|---|",
    ]
    for key, label in (
        ("bridged", "State -> `dynqos edge ros2` -> PoseStamped"),
        ("bare_zenoh", "floor: bare zenoh responder, same sizes"),
    ):
        f = latency[key]
        rows.append(f"| {label} | {f['p50_ms']:.3f} | {f['p99_ms']:.3f} | {f['mean_ms']:.3f} |")
    rows += ["", "| drones (State 20 Hz, status 5 Hz) | bridge CPU (share of a core) |", "|---|---|"]
    rows += [f"| {r['drones']} | {r['core_share']:.3f} |" for r in cpu["rows"]]
    rows += [
        f"| per drone (slope) | {cpu['per_drone_core_share']:.4f} |",
        "",
        "| control loop at 100 Hz | p50 (ms) | p99 (ms) | each phase's p50 (ms) |",
        "|---|---|---|---|",
    ]
    for key, label in (
        ("off", "bridge off"),
        ("floor", "floor: a bare zenoh subscriber of the states"),
        ("on", "bridge on, a ROS listener on every topic"),
    ):
        f = loop[key]
        phases = ", ".join(f"{p:.2f}" for p in f["phase_p50_ms"])
        rows.append(f"| {label} | {f['p50_ms']:.3f} | {f['p99_ms']:.3f} | {phases} |")
    rows.append(
        f"\nthe loop's p50 with the bridge on: {loop['change_p50'] * 100:+.1f}%; with a bare subscriber "
        f"of the states: {loop['floor_change_p50'] * 100:+.1f}%"
    )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--round-trips", type=int, default=1000, help="per path (default 1000)")
    parser.add_argument("--seconds", type=float, default=5.0, help="measured per fleet size (default 5)")
    parser.add_argument(
        "--quick", action="store_true", help="smoke mode: 200 round trips in 1 round, 0.5 s per size"
    )
    args = parser.parse_args(argv)
    if args.round_trips < 2 * BLOCK:
        parser.error(f"--round-trips must be at least {2 * BLOCK}")
    if not 0.2 <= args.seconds <= 600:
        parser.error("--seconds must be in 0.2..600")
    # each phase starts its own bridge (or subscriber): the smoke's one round starts a quarter as many
    result = run(200, 0.5, 1) if args.quick else run(args.round_trips, args.seconds)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
