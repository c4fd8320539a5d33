"""Benchmark: what the edge costs per drone it serves over zenoh with a fleet's real message mix, beside
the bare OSQP solve.

A load client (one zenoh session standing in for the fleet) sends each of D drones' mix through a
router to the MPC, planner, detector and QoS agent, as the fleet scenarios' drones do (docs/fleet.md):
its State every 50 ms on the priority flow, its SupervisorStatus at 5 Hz, its QosRequest every second,
and its camera's RGB-D frames at 15 fps in 1 KB parts, rendered in the fleet's world along its mission
at the size that offers 17 Mbit/s at the fleet's scale. It reads back what the drones would (commands,
acks, references, grants). Each edge process's CPU seconds over the measured span (/proc/PID/stat)
for D = 1, 2, 4, 8 drones; the cost per drone is the slope of a least-squares line through them (the
intercept is what a served-nobody edge costs). Beside it, the bare OSQP solve of the MPC's QP at
20 Hz (the same floor `mpc_step` measures): the part of the MPC's cost no transport can remove. Then
the same sweep once more with the MPC replaced by a minimal Python MPC (`zenoh_echo --mpc`: decode,
solve, answer): what any Python MPC on zenoh costs per drone on this load, the floor of the ratio
between the MPC process and its bare solves.

Run: dynqos bench edge_per_drone (suite settings), or with its own options:
  python -m dynqos.bench.edge_per_drone [--seconds 5] [--quick] [--out FILE]
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import dataclass
from typing import Any

from dynqos.bench.report import bench_parser, emit, judged, provenance
from dynqos.bench.rig import router_rig
from dynqos.common import keys
from dynqos.common.config import ControlConfig, MpcConfig, ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import CameraFrame, Message, QosRequest, State, SupervisorStatus
from dynqos.common.modes import ControlSource, SupervisorState
from dynqos.common.modes import Flow as FlowMode
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Publisher, Received, Role, open_bus
from dynqos.experiment.processes import Processes, cpu_s

PERIOD_S = 0.05  # the State period: a tick; the camera sends in 3 ticks of 4 (15 fps), the status in 1 of 4
EDGE = ("router", "mpc", "planner", "detector", "qos")
TARGET_CORE_SHARE_PER_DRONE = 0.10  # the edge should serve a drone in a tenth of a core
FLOOR = "minimal-mpc"  # bench/zenoh_echo.py --mpc


@dataclass(frozen=True)
class Frames:
    """One drone's camera, encoded once: (kind, encoding, width, height, intrinsics, parts) per frame half."""

    halves: list[tuple[str, str, int, int, tuple[float, float, float, float], list[bytes]]]


def _frames(count: int) -> Frames:
    """RGB-D frames as fleet-arbiter's first drone sees them: its world, mission, camera size and parts."""
    from dynqos.onboard.camera import DEPTH_ENCODING, encode_depth, encode_rgb
    from dynqos.onboard.pacing import split
    from dynqos.plan.camera_sizing import flight_views
    from dynqos.plan.scenario import builtin_scenario, fleet_configs
    from dynqos.sim.vehicle.camera import SimCamera
    from dynqos.sim.vehicle.world import load_world

    scenario = builtin_scenario("fleet-arbiter")
    _, drones = fleet_configs(scenario, zenoh=ZenohConfig(), fc_base=14540, gcs_port=14550)
    config = next(iter(drones.values()))
    onboard = config.onboard
    camera = SimCamera(load_world(onboard.world_file), onboard.camera_width, onboard.camera_height)
    halves = []
    for pose in flight_views(config, count):
        raw = camera.grab(pose)
        assert raw is not None
        assert raw.depth_m is not None
        h, w = raw.rgb.shape[:2]
        for kind, encoding, data in (
            ("rgb", "jpeg", encode_rgb(raw.rgb, onboard.jpeg_quality)),
            ("depth", DEPTH_ENCODING, encode_depth(raw.depth_m)),
        ):
            halves.append((kind, encoding, w, h, raw.intrinsics, split(data, onboard.camera_part_bytes)))
    return Frames(halves)


def _status(uav: str, seq: int, now: int) -> SupervisorStatus:
    """A status as a drone in q2 sends it 5 times a second, with its four RTT samples."""
    return SupervisorStatus(
        uav=uav,
        seq=seq,
        stamp_ns=now,
        state=SupervisorState.Q2,
        flow=FlowMode.PRIORITY,
        camera_rate_factor=1.0,
        control_source=ControlSource.EDGE,
        camera_flow=FlowMode.PRIORITY,
        latency="LL",
        risk="HR",
        watchdog=False,
        t_cam_ms=50.0,
        t_cc_ms=20.0,
        spaciousness_m=2.3,
        p_cam=0.1,
        p_cc=0.0,
        p_lat=0.05,
        p_cs=0.9,
        prev_state=SupervisorState.Q1,
        cause="HR",
        changed_ns=0,
        rtt_ms=20.0,
        camera_latency_ms=50.0,
        rtt_samples_ms=(20.0, 21.0, 19.5, 20.2),
        camera_latency_samples_ms=(50.0, 52.0, 49.0),
        camera_bytes=seq * 1000,
    )


class _Drone:
    def __init__(self, bus: Any, uav: str) -> None:
        self.uav = uav
        self.presence = bus.declare_token(keys.drone_presence(uav))  # as its daemon does
        self.state = bus.publisher(
            keys.uplink(uav, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True
        )
        self.status = bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.STATUS), Priority.DATA_HIGH)
        self.qos = bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.QOS), Priority.DATA_HIGH)
        self.rgb = bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.CAMERA_RGB), Priority.DATA)
        self.depth = bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.CAMERA_DEPTH), Priority.DATA)

    def publishers(self) -> list[Publisher]:
        return [self.state, self.status, self.qos, self.rgb, self.depth]


def _tick(drone: _Drone, index: int, tick: int, seq: int, frames: Frames) -> None:
    now = time.monotonic_ns()
    messages: list[tuple[Publisher, Message]] = [
        (
            drone.state,
            State(
                uav=drone.uav,
                seq=seq,
                stamp_ns=now,
                pos_m=(0.1 * index, 0.0, -1.5),
                vel_mps=(0.0, 0.0, 0.0),
                quat=(1.0, 0.0, 0.0, 0.0),
                rtt_est_ms=20.0,
            ),
        )
    ]
    if tick % 4 == 0:
        messages.append((drone.status, _status(drone.uav, seq, now)))
    if tick % 20 == 0:
        messages.append((drone.qos, QosRequest(uav=drone.uav, seq=seq, stamp_ns=now, want=True, risk="HR")))
    for pub, message in messages:
        pub.put(message)
    if tick % 4 != 3:  # 15 frames a second from 20 ticks
        frame = (tick - tick // 4) % (len(frames.halves) // 2)
        for pub, (kind, encoding, w, h, intrinsics, parts) in zip(
            (drone.rgb, drone.depth), frames.halves[2 * frame : 2 * frame + 2], strict=True
        ):
            for part, payload in enumerate(parts):
                pub.put(
                    CameraFrame(
                        uav=drone.uav,
                        seq=seq,
                        stamp_ns=now,
                        kind=kind,
                        encoding=encoding,
                        width=w,
                        height=h,
                        intrinsics=intrinsics,
                        payload=payload,
                        part=part,
                        parts=len(parts),
                    )
                )


def _load(
    zcfg: ZenohConfig, procs: Processes, drones: int, seconds: float, frames: Frames, edge: tuple[str, ...]
) -> dict[str, Any]:
    bus = open_bus(zcfg, Role.DRONE)
    try:
        back: BoundedQueue[Received] = BoundedQueue(200_000)
        for kind in (Downlink.COMMAND, Downlink.CAMERA_ACK, Downlink.REFERENCE, Downlink.QOS_GRANT):
            bus.subscribe(keys.downlink_all_drones(kind), back)
        # new ids per size and sweep: fresh controllers
        fleet = [_Drone(bus, f"b{drones}{'f' if FLOOR in edge else 'u'}{i}") for i in range(drones)]
        if not all(pub.wait_matched(30) for d in fleet for pub in (d.state, d.rgb)):
            raise RuntimeError("the edge services never subscribed")
        seq0 = time.monotonic_ns() // 1_000_000
        warmup, ticks = 20, round(seconds / PERIOD_S)
        start = time.perf_counter()
        used_before: dict[str, float] = {}
        for tick in range(warmup + ticks):
            if tick == warmup:
                used_before = {name: cpu_s(procs.procs[name].pid) or 0.0 for name in edge}
                t_measured = time.perf_counter()
                back.drain()
            for index, drone in enumerate(fleet):
                _tick(drone, index, tick, seq0 + tick + 1, frames)
            delay = start + (tick + 1) * PERIOD_S - time.perf_counter()
            if delay > 0:
                time.sleep(delay)  # the fleet's period: pacing the load, not synchronising with anything
        span = time.perf_counter() - t_measured
        used = {name: ((cpu_s(procs.procs[name].pid) or 0.0) - used_before[name]) / span for name in edge}
        answered = sum(1 for item in back.drain() if item.key.endswith("down/cmd"))
    finally:
        bus.close()
    return {
        "drones": drones,
        "core_share": {k: round(v, 4) for k, v in used.items()},
        "edge_core_share": round(sum(used.values()), 4),
        "commands_per_s": answered / span,
    }


def _slope(xs: list[float], ys: list[float]) -> tuple[float, float]:
    """Least squares y = a + b x: (a, b)."""
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    b = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx if sxx else 0.0
    return my - b * mx, b


def bare_osqp_share(steps: int) -> float:
    """One drone's bare OSQP solves at 20 Hz as a share of a core (mpc_step's floor, horizon 20)."""
    from dynqos.bench.mpc_step import step_vs_floor

    median_ms = float(step_vs_floor(ControlConfig().horizon, steps)["bare_osqp"]["median_ms"])
    return median_ms / 1000 / PERIOD_S


def run(seconds: float, quick: bool) -> dict[str, Any]:
    counts = [1, 2] if quick else [1, 2, 4, 8]
    frames = _frames(3 if quick else 12)
    rows = []
    toml = '[qos]\nbackend = "links"\n[mpc]\nidle_timeout_s = 2\n[detector]\n'
    floor_rows = []
    with router_rig(toml) as (zcfg, procs):
        for name in EDGE[1:]:
            procs.start(name, ["edge", name])
        for count in counts:
            rows.append(_load(zcfg, procs, count, seconds, frames, EDGE))
        # The same load once more with a minimal Python MPC in the MPC's place: the floor of the ratio
        procs.stop("mpc")
        procs.start(FLOOR, ["--mpc"], program=[sys.executable, "-m", "dynqos.bench.zenoh_echo"])
        for count in counts:
            floor_rows.append(_load(zcfg, procs, count, seconds, frames, (FLOOR,)))
    xs = [float(r["drones"]) for r in rows]
    per_process = {name: _slope(xs, [r["core_share"][name] for r in rows])[1] for name in EDGE}
    idle, per_drone = _slope(xs, [r["edge_core_share"] for r in rows])
    floor = _slope([float(r["drones"]) for r in floor_rows], [r["core_share"][FLOOR] for r in floor_rows])[1]
    bare = bare_osqp_share(50 if quick else 400)
    return {
        "benchmark": "edge_per_drone",
        **provenance(),
        "seconds_per_size": seconds,
        "rows": rows,
        "per_drone_core_share": per_drone,
        "per_drone_core_share_by_process": per_process,
        "idle_core_share": idle,
        "bare_osqp_core_share_per_drone": bare,
        "minimal_mpc_rows": floor_rows,
        "minimal_mpc_core_share_per_drone": floor,
        "mpc_over_bare": per_process["mpc"] / bare,
        "minimal_mpc_over_bare": floor / bare,
        "mpc_config": {"horizon": ControlConfig().horizon, "max_iter": MpcConfig().max_iter},
    }


def verdict(result: dict[str, Any]) -> str:
    share = result["per_drone_core_share"]
    return judged(
        share <= TARGET_CORE_SHARE_PER_DRONE,
        f"{share:.1%} of a core per drone served at the edge "
        f"(bare OSQP {result['bare_osqp_core_share_per_drone']:.2%}); target <= "
        f"{TARGET_CORE_SHARE_PER_DRONE:.0%}",
    )


def markdown(result: dict[str, Any]) -> str:
    rows = [
        "| drones | edge (share of a core) | " + " | ".join(EDGE) + " | commands/s |",
        "|---|---|" + "---|" * len(EDGE) + "---|",
    ]
    rows += [
        f"| {r['drones']} | {r['edge_core_share']:.3f} | "
        + " | ".join(f"{r['core_share'][n]:.3f}" for n in EDGE)
        + f" | {r['commands_per_s']:.0f} |"
        for r in result["rows"]
    ]
    by = result["per_drone_core_share_by_process"]
    rows += [
        "",
        f"Per drone (slope): {result['per_drone_core_share']:.3f} of a core "
        f"({', '.join(f'{n} {by[n]:.3f}' for n in EDGE)}); an edge serving nobody: "
        f"{result['idle_core_share']:.3f}. Bare OSQP at 20 Hz: "
        f"{result['bare_osqp_core_share_per_drone']:.4f}.",
        "",
        f"The MPC process per drone: {result['mpc_over_bare']:.1f}x its bare solves; a minimal Python MPC "
        f"on the same load (decode, solve, answer; `zenoh_echo --mpc`): "
        f"{result['minimal_mpc_core_share_per_drone']:.4f} of a core, "
        f"{result['minimal_mpc_over_bare']:.1f}x.",
    ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__)
    parser.add_argument("--seconds", type=float, default=5.0, help="measured per fleet size (default 5)")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 1 and 2 drones for 1 s")
    args = parser.parse_args(argv)
    if not 0.5 <= args.seconds <= 120:
        parser.error("--seconds must be in 0.5..120")
    result = run(1.0 if args.quick else args.seconds, args.quick)
    return emit(result, markdown(result), args.out, verdict(result))


if __name__ == "__main__":
    sys.exit(main())
