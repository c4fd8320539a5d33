"""Floors for the benchmarks: bare zenoh-python processes beside which dynqos's own are measured.

- `--reply-bytes N`: answers every sample on `bench/ping` with N bytes on `bench/pong`, at the same
  priority and express setting as the MPC's Command, through the same router: what a round trip costs
  with zenoh alone, without our messages, queues or the MPC (`bench/control_loop.py`).
- `--listen KEY`: a subscriber that does nothing (the floor of any watcher, `bench/observability.py`).
- `--mpc`: the least a Python MPC over zenoh does (`bench/edge_per_drone.py`): every drone's State
  decoded (one wildcard subscriber, on zenoh's thread), the MPC's QP solved (`MpcProblem.solve`, one per
  drone, holding the drone where it is), a Command built from the solution and put on the drone's
  command key. Without references, delay compensation, replicas, fencing, queues, counters or health.
- `--fixed`: the same without the solve: each State answered with a Command of fixed inputs (as many as
  the MPC sends): what receiving and answering alone cost, the floor of any MPC process
  (`bench/fleet_zenoh.py`).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from typing import Any

import numpy as np
import zenoh

from dynqos.common import keys
from dynqos.common.config import load_config
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Command, State, decode, encode
from dynqos.common.transport import Role, open_session
from dynqos.edge.mpc.problem import MpcProblem

PING, PONG = "bench/ping", "bench/pong"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--reply-bytes", type=int, default=0, help="payload size of each answer")
    parser.add_argument(
        "--listen",
        metavar="KEY",
        help="only subscribe to KEY and do nothing with it (the observability floor)",
    )
    parser.add_argument("--mpc", action="store_true", help="answer each drone's State as a minimal MPC")
    parser.add_argument("--fixed", action="store_true", help="answer each drone's State with a fixed Command")
    parser.add_argument("--config", required=True, help="dynqos config (its [zenoh] section: the router)")
    args = parser.parse_args(argv)
    session = open_session(load_config(args.config).zenoh, Role.EDGE)
    if args.listen:  # a second subscriber of the drone's states, as cheap as zenoh makes one
        subscriber = session.declare_subscriber(args.listen, lambda _sample: None)
    elif args.mpc or args.fixed:
        # on zenoh's receiving thread (no hand-over to a Python thread): the least a process can do
        answer = zenoh.handlers.Callback(_MinimalMpc(session, solve=args.mpc), indirect=False)
        subscriber = session.declare_subscriber(keys.uplink_all_drones(Stream.STATE), answer)
    else:
        if args.reply_bytes <= 0:
            parser.error("--reply-bytes is required (or --listen KEY, --mpc or --fixed)")
        reply = bytes(args.reply_bytes)
        pong = session.declare_publisher(PONG, priority=zenoh.Priority.REAL_TIME, express=True)
        subscriber = session.declare_subscriber(PING, lambda _sample: pong.put(reply))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    print(json.dumps({"ready": True, "service": "zenoh_echo"}), flush=True)
    stop.wait()
    subscriber.undeclare()  # type: ignore[no-untyped-call]
    session.close()  # type: ignore[no-untyped-call]
    return 0


class _MinimalMpc:
    """`--mpc`: decode, solve, answer; nothing else. `solve` False (`--fixed`): decode, answer."""

    def __init__(self, session: zenoh.Session, solve: bool = True) -> None:
        self.session = session
        self.solve = solve
        self.drones: dict[str, tuple[MpcProblem, Any]] = {}
        template = MpcProblem()
        self.dt_s = template.dt_s
        self.fixed = ((0.0, 0.0, 0.0),) * template.mpc.command_steps

    def __call__(self, sample: zenoh.Sample) -> None:
        arrival_ns = time.monotonic_ns()  # where the MPC takes its arrival: after the bytes, before decoding
        state = decode(sample.payload.to_bytes())
        if not isinstance(state, State):
            return
        drone = self.drones.get(state.uav)
        if drone is None:
            key = keys.downlink(state.uav, Downlink.COMMAND)
            publisher = self.session.declare_publisher(  # as the MPC declares its Command publisher
                key,
                priority=zenoh.Priority.REAL_TIME,
                express=True,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            drone = self.drones[state.uav] = (MpcProblem(), publisher)
        problem, publisher = drone
        accel = self.fixed
        if self.solve:
            x0 = np.array([*state.pos_m, *state.vel_mps])
            hold = np.tile(np.concatenate([x0[:3], np.zeros(3)]), (problem.horizon + 1, 1))
            inputs = problem.solve(x0, hold)[: problem.mpc.command_steps]  # as many steps as the MPC sends
            accel = tuple(map(tuple, inputs.tolist()))
        command = Command(
            uav=state.uav,
            seq=state.seq,
            state_seq=state.seq,
            state_stamp_ns=state.stamp_ns,
            edge_hold_ns=time.monotonic_ns() - arrival_ns,
            dt_s=self.dt_s,
            accel_mps2=accel,
            yaw_rad=(0.0,) * len(accel),
        )
        publisher.put(encode(command))


if __name__ == "__main__":
    sys.exit(main())
