"""`dynqos sim cell` and `dynqos sim vehicle`: the stand-ins for the 5G cell and the drone's hardware."""

from __future__ import annotations

import argparse

from dynqos.cli.options import Commands, common_options, metrics_options, path_or_none, with_metrics
from dynqos.common.config import Config
from dynqos.sim.vehicle import MAX_INSTANCE  # the package alone: the CLI starts without the simulator

CELL = (
    "A user-space 5G uplink: one TCP listener per bearer (QoS flow) forwarding to an edge router port, a UE "
    "buffer per bearer, a resource-fair scheduler with relative priority weights every TTI, virtual "
    "background users, base delay and jitter, and timeline events. Configured by the [cell] table of the "
    "config file (see docs/cell.md). Prints one JSON line with the bearer ports when ready; stops on "
    "SIGINT/SIGTERM or after --duration."
)
VEHICLE = (
    "A rigid-body quadrotor with a PX4-like flight controller (arming, takeoff, hold, land, offboard with "
    "PX4's custom modes and offboard-loss failsafe) speaking MAVLink 2 over UDP: the offboard link binds "
    "[vehicle] offboard_bind_port (14580) and sends to offboard_remote_port (14540); the ground-station "
    "link binds 18570 and sends to 14550. Prints one JSON line when ready. Contacts with the world's "
    "obstacles are logged and counted."
)
PX4 = (
    "Boots PX4 instance N from [px4] dir (a folder with bin/px4 and etc/, such as PX4's "
    "build/px4_sitl_default), with the SIH quadrotor unless PX4_SYS_AUTOSTART names another airframe and "
    "the parameters dynqos flies with ([px4] params over them; docs/px4.md). PX4 keeps its own ports: "
    "the onboard daemon listens on udpin:127.0.0.1:14540+N. PX4's console goes to DIR/console.log, its "
    "ULog to DIR/log/. Prints one JSON line when PX4's start-up is done; SIGTERM stops PX4 cleanly."
)


def add(commands: Commands) -> None:
    sim = commands.add_parser(
        "sim",
        parents=[common_options(1)],
        help="simulators: the emulated 5G cell, and a simulated quadrotor with its camera behind a MAVLink "
        "flight controller",
    )
    simulators = sim.add_subparsers(dest="sim_command", metavar="SIMULATOR", required=True)
    cell = simulators.add_parser(
        "cell",
        parents=[common_options(2)],
        description=CELL,
        help="run the 5G cell emulator between the drone and the edge router",
    )
    cell.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (default: until stopped)"
    )
    cell.add_argument("--out", metavar="DIR", help="write per-interval records to DIR/cell.csv")
    metrics_options(cell)
    cell.set_defaults(handler=run_cell)

    vehicle = simulators.add_parser(
        "vehicle",
        parents=[common_options(2)],
        description=VEHICLE,
        help="run the simulated quadrotor that speaks MAVLink like PX4 SITL",
    )
    clock = vehicle.add_mutually_exclusive_group()
    clock.add_argument(
        "--realtime",
        dest="clock",
        action="store_const",
        const="realtime",
        help="pace simulated time to the wall clock x --speed (the default; for the demo and real peers)",
    )
    clock.add_argument(
        "--lockstep",
        dest="clock",
        action="store_const",
        const="lockstep",
        help="advance 20 ms of simulated time each time the peer answers the telemetry with a setpoint: "
        "as fast as the peer, deterministic with [vehicle] seed (for tests)",
    )
    vehicle.add_argument(
        "--world", metavar="FILE", help="world file (TOML or JSON) for contact checks (default: the arena)"
    )
    vehicle.add_argument(
        "--speed", type=float, metavar="X", help="simulated seconds per wall second (default 1)"
    )
    vehicle.add_argument("--duration", type=float, metavar="S", help="stop after S simulated seconds")
    vehicle.add_argument(
        "--instance",
        type=int,
        default=0,
        metavar="N",
        help="vehicle N of a fleet, as PX4 SITL numbers them: MAVLink system id N+1, the offboard and "
        "ground-station ports + N (14580+N -> 14540+N, 18570+N -> 14550: one ground station sees every "
        f"vehicle); 0..{MAX_INSTANCE} (default 0)",
    )
    vehicle.set_defaults(handler=run_vehicle)
    _add_px4(simulators)


def _add_px4(simulators: Commands) -> None:
    px4 = simulators.add_parser(
        "px4",
        parents=[common_options(2)],
        description=PX4,
        help="run a real PX4 SITL (PX4's own flight stack) in place of the simulated quadrotor",
    )
    px4.add_argument(
        "--instance",
        type=int,
        default=0,
        metavar="N",
        help="PX4 instance N: MAVLink system id N+1, offboard link to 14540+N (PX4 listens on 14580+N), "
        "ground station to 14550; 0..9 (default 0)",
    )
    px4.add_argument(
        "--workdir",
        metavar="DIR",
        help="PX4's working directory: parameters, dataman, log/ with the ULog (default ./px4-i<N>)",
    )
    px4.add_argument("--px4-dir", metavar="DIR", help="PX4's folder, over [px4] dir")
    px4.add_argument(
        "--start",
        metavar="N,E",
        help="where it stands, metres north and east of the fleet's common origin (default 0,0): PX4 boots "
        "there and is told the common origin, so that every instance reports positions in one frame",
    )
    px4.set_defaults(handler=run_px4)


def run_cell(args: argparse.Namespace, config: Config) -> int:
    from dynqos.sim.network import service

    return service.run(with_metrics(args, config), out_dir=path_or_none(args.out), duration_s=args.duration)


def run_vehicle(args: argparse.Namespace, config: Config) -> int:
    from dynqos.sim.vehicle import service

    lockstep = None if args.clock is None else args.clock == "lockstep"
    return service.run(
        config,
        instance=args.instance,
        world_file=args.world,
        lockstep=lockstep,
        speed=args.speed,
        duration_s=args.duration,
    )


def run_px4(args: argparse.Namespace, config: Config) -> int:
    from dataclasses import replace
    from pathlib import Path

    from dynqos.sim.vehicle import px4_sitl

    if args.px4_dir:
        config = replace(config, px4=replace(config.px4, dir=args.px4_dir))
    workdir = Path(args.workdir) if args.workdir else Path(f"px4-i{args.instance}")
    start = _north_east(args.start) if args.start else (0.0, 0.0)
    return px4_sitl.run(config, instance=args.instance, workdir=workdir, start_m=start)


def _north_east(text: str) -> tuple[float, float]:
    from dynqos.common.errors import DynqosError

    try:
        north, east = (float(v) for v in text.split(","))
    except ValueError:
        raise DynqosError(f"--start takes N,E in metres (e.g. 2.5,-1), got {text!r}") from None
    if not all(abs(v) <= 1e4 for v in (north, east)):
        raise DynqosError(f"--start must be within 10 km of the origin, got {text!r}")
    return north, east
