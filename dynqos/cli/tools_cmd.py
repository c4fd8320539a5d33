"""`dynqos bench`, `dynqos health`, `dynqos certs`, `dynqos version`, and `dynqos view` / `dynqos record`:
the tools around a flight."""

from __future__ import annotations

import argparse
from pathlib import Path

from dynqos import __version__
from dynqos.cli.options import Commands, common_options, described
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError

BENCH = (
    "Runs each benchmark against its floor and target (all by default: supervisor_step, mpc_step, "
    "control_loop, fleet_zenoh, edge_scale, edge_per_drone, camera_rate, onboard_camera, vehicle_sim, "
    "cell_forward, supervisor_reaction, fleet_flight, observability, ros2_bridge), prints one verdict line "
    "each, and writes bench-results.json (every figure) and bench-results.md (the tables) into --out. "
    "Benchmarks report; the exit code is 0 whatever the verdicts. docs/benchmarks.md explains each one."
)
CERTS = (
    "Writes into --out (made 0700): ca.pem and ca-key.pem (kept and reused if present), router.pem (server "
    "and client auth; names: localhost, 127.0.0.1 and each --router-host), one identity per edge service "
    "(edge-mpc, edge-planner, edge-fleet-planner, edge-detector, edge-qos, edge-ros2: each may touch only "
    "its own keys) and "
    "<id>.pem per --drone (CN = drone id, matched by the router's access control; a ROS 2 node's "
    "identity is issued the same way, its name in [zenoh] acl_ros2_clients), each with its "
    "<name>-key.pem (mode 0600, written through a new file, never through a link). Pairs that exist and "
    "are still valid are kept unless --force, so adding a drone re-issues nothing else. No certificate "
    "outlives the CA. For production use your own PKI with the same common names; rotation and "
    "revocation: docs/security.md."
)
OBSERVE = (
    "poses, the reference path, the world's obstacles and the risk zone as a 3D scene, the RGB camera with "
    "its detections, the supervisor's status, the QoS grants and decisions, and the supervisor's "
    "transitions as log lines. Connects to the router at [zenoh] edge_host as an edge client. Stops on "
    "SIGTERM or Ctrl-C, closing the file whole."
)


def add(commands: Commands) -> None:
    own = common_options(1, settings=False)
    bench = commands.add_parser(
        "bench",
        parents=[own],
        description=BENCH,
        help="run the benchmarks (what the runtime costs, beside its floor) and write bench-results.json",
    )
    bench.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all)")
    bench.add_argument("--smoke", action="store_true", help="each in a few seconds (what CI runs)")
    bench.add_argument(
        "--repeat",
        type=int,
        default=1,
        metavar="N",
        help="run each N times and report the spread (default 1)",
    )
    bench.add_argument("--out", default=".", metavar="DIR", help="where to write the results (default .)")
    bench.set_defaults(handler=run_bench, own_config="each benchmark sets up what it measures")

    health = commands.add_parser(
        "health",
        parents=[own],
        help="check a service's health file (exit 0 if fresh): for Kubernetes exec probes",
        description="Prints the last health line written by a service started with --health-file FILE "
        "and exits 0 if it is at most --max-age seconds old; otherwise says why and exits 2.",
    )
    health.add_argument("health_path", metavar="FILE", help="the service's --health-file")
    health.add_argument(
        "--max-age", type=float, default=15.0, metavar="S", help="oldest acceptable line (default 15 s)"
    )
    health.set_defaults(handler=check_health, own_config="it reads only the health file")

    _add_keys(commands, own)

    for name, text in (
        (
            "view",
            "serve the drones live to the Foxglove app over its WebSocket protocol (docs/observability.md)",
        ),
        ("record", "record the drones to an MCAP file that Foxglove and the mcap tools open"),
    ):
        observe = commands.add_parser(
            name, parents=[common_options(1)], help=text, description=described(text, OBSERVE)
        )
        observe.add_argument("--uav", metavar="ID", help="only this drone (default: every drone)")
        observe.add_argument("--world", metavar="FILE", help="the world to draw (default: the simulator's)")
        observe.add_argument("--no-camera", action="store_true", help="leave the camera images out")
        observe.add_argument("--scenario", default="", help=argparse.SUPPRESS)  # for the demo's metadata
        if name == "view":
            observe.add_argument("--port", type=int, default=8765, help="WebSocket port (default 8765)")
            observe.add_argument(
                "--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)"
            )
            observe.add_argument("--record", metavar="FILE.mcap", help="also record to this MCAP file")
        else:
            observe.add_argument("--out", metavar="FILE.mcap", required=True, help="the MCAP file to write")
            observe.add_argument(
                "--ros2",
                action="store_true",
                help="write ROS 2 messages (ros2msg schemas, cdr), the topics of `dynqos edge ros2`, for "
                "`ros2 bag` and Foxglove's ROS 2 support; needs the ros2 extra (docs/ros2.md)",
            )
        observe.set_defaults(handler=observe_flight)

    version = commands.add_parser("version", help="print the version", parents=[own])
    version.set_defaults(handler=print_version, own_config="it reads nothing")


def _add_keys(commands: Commands, own: argparse.ArgumentParser) -> None:
    """`dynqos certs` and `dynqos signing-key`: the keys a deployment needs."""
    certs = commands.add_parser(
        "certs",
        parents=[own],
        description=CERTS,
        help="make a development CA and mTLS certificates: the router, each edge service, each drone",
    )
    certs.add_argument("--out", metavar="DIR", required=True, help="folder for the PEM files")
    certs.add_argument(
        "--drone", metavar="ID", action="append", default=[], dest="drones", help="a drone id (repeatable)"
    )
    certs.add_argument(
        "--task",
        metavar="NAME",
        action="append",
        default=[],
        dest="tasks",
        help="a task of your own (repeatable): its service's identity edge-task-NAME (docs/offload.md)",
    )
    certs.add_argument(
        "--router-host",
        metavar="NAME",
        action="append",
        default=[],
        dest="router_hosts",
        help="a DNS name or IP the drones dial the router by (repeatable), e.g. dynqos-router.dynqos.svc",
    )
    certs.add_argument(
        "--days", type=int, default=365, metavar="N", help="validity of new certificates (default 365 days)"
    )
    certs.add_argument(
        "--ca-days", type=int, default=1825, metavar="N", help="validity of a new CA (default 1825 days)"
    )
    certs.add_argument(
        "--force", action="store_true", help="issue every certificate again, even those still valid"
    )
    certs.set_defaults(handler=make_certs, own_config="it reads only its own options")

    signing = commands.add_parser(
        "signing-key",
        parents=[own],
        help="make a MAVLink 2 signing key for the drone's flight-controller link (docs/onboard.md)",
        description="Writes 32 random bytes as 64 hexadecimal characters to --out, a new file of mode 0600 "
        "(never through a link). Give the same file to [onboard] mavlink_signing_key and, for the "
        "simulator, [vehicle] signing_key; provision a real PX4 or ArduPilot with it over USB (MAVProxy: "
        "signing setup). The key is never printed or logged.",
    )
    signing.add_argument("--out", metavar="FILE", required=True, help="the key file to write")
    signing.add_argument("--force", action="store_true", help="replace an existing key file")
    signing.set_defaults(handler=make_signing_key, own_config="it reads only its own options")


def run_bench(args: argparse.Namespace, config: Config) -> int:
    from dynqos.bench.suite import run_suite

    run_suite(args.names, smoke=args.smoke, repeat=args.repeat, out=Path(args.out))
    return 0


def check_health(args: argparse.Namespace, config: Config) -> int:
    from dynqos.edge.health import check_health

    if not 0 < args.max_age <= 3600:
        raise DynqosError(f"--max-age must be in (0, 3600] s, got {args.max_age}")
    print(check_health(Path(args.health_path), args.max_age))
    return 0


def make_signing_key(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.mavsign import write_key

    print(f"wrote a MAVLink signing key to {write_key(args.out, force=args.force)} (mode 0600)")
    return 0


def make_certs(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.certs import make_dev_pki
    from dynqos.common.errors import KeyExprError

    if not args.drones:
        raise DynqosError("give at least one --drone ID")
    try:
        issued = make_dev_pki(
            Path(args.out),
            args.drones,
            args.router_hosts,
            days=args.days,
            ca_days=args.ca_days,
            force=args.force,
            tasks=args.tasks,
        )
    except KeyExprError as exc:
        raise DynqosError(f"--drone or --task: {exc}") from None
    for name, pair in issued.items():
        print(f"{name}: {pair.cert} {pair.key}{' (kept)' if pair.kept else ''}")
    print(f"ca: {Path(args.out) / 'ca.pem'}")
    return 0


def observe_flight(args: argparse.Namespace, config: Config) -> int:
    from dynqos.observers import observer

    if getattr(args, "ros2", False):
        from dynqos.observers import ros2_recording

        return ros2_recording.run(config, Path(args.out), uav=args.uav, camera=not args.no_camera)
    view = args.command == "view"
    record = Path(args.record) if view and args.record else (None if view else Path(args.out))
    return observer.run(
        config,
        view=view,
        record=record,
        uav=args.uav,
        world_file=args.world,
        camera=not args.no_camera,
        host=getattr(args, "host", "127.0.0.1"),
        port=getattr(args, "port", 8765),
        scenario=args.scenario,
    )


def print_version(args: argparse.Namespace, config: Config) -> int:
    print(f"dynqos {__version__}")
    return 0
