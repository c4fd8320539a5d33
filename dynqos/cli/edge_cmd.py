"""`dynqos edge SERVICE` and `dynqos onboard`: the two halves of the loop, each from its own `run`."""

from __future__ import annotations

import argparse
import importlib
import os
from collections.abc import MutableMapping

from dynqos.cli.options import (
    Commands,
    common_options,
    described,
    metrics_options,
    path_or_none,
    with_metrics,
)
from dynqos.common.config import Config
from dynqos.common.errors import ConfigError

SERVICES = {  # name -> (its module, what it does)
    "router": (
        "dynqos.edge.router",
        "the zenoh router, listening on the default-flow (7447) and priority-flow (7448) ports",
    ),
    "mpc": (
        "dynqos.edge.mpc.service",
        "the MPC position controller: one OSQP controller per drone, answering each State with a Command",
    ),
    "planner": (
        "dynqos.edge.planner.service",
        "the mission planner: publishes each drone's reference trajectory ([planner] config)",
    ),
    "fleet-planner": (
        "dynqos.edge.planner.fleet_service",
        "the fleet's mission planner: assigns [fleet_plan] tasks to the drones, routes and books them by "
        "the operator's predicted connectivity, and sends each drone its legs (docs/planning.md)",
    ),
    "detector": (
        "dynqos.edge.detector.service",
        "the circle detector: acks every camera frame, detects circles in RGB, locates them with depth",
    ),
    "ros2": (
        "dynqos.edge.ros2.service",
        "the ROS 2 face: each drone's pose, odometry, /tf, camera and status as rmw_zenoh topics that "
        "ROS 2 nodes see natively ([ros2] config; docs/ros2.md)",
    ),
    "qos": (
        "dynqos.edge.qos.agent",
        "the QoS agent: turns the drones' requests for priority into what the network needs ([qos] "
        "backend: links, or camara for CAMARA Quality-on-Demand sessions; docs/qos.md)",
    ),
}
ROUTER = (
    "Listens on [zenoh] router_listen_host (loopback by default), one port per flow; with tls = true it "
    "takes only mutual-TLS sessions and applies the access control of [zenoh] acl_drones."
)
CLIENT = "Connects to the router at [zenoh] edge_host:default_port as a client."
ONBOARD = (
    "Connects to the flight controller ([onboard] mavlink_url, default udpin:127.0.0.1:14540 like PX4 "
    "SITL's offboard link) and to the edge router on two flows, streams state and camera, flies the "
    "edge's commands or the fallback PID, and runs the QoS supervisor. It never arms by itself: --takeoff "
    "arms, takes off to [onboard] takeoff_alt_m and starts offloading. SIGTERM: hold (or land) and exit."
)


def add(commands: Commands) -> None:
    edge = commands.add_parser(
        "edge",
        help="edge services: router, mpc, planner, fleet-planner, detector, ros2, qos; serve: your own task",
        parents=[common_options(1)],
    )
    services = edge.add_subparsers(dest="edge_command", metavar="SERVICE", required=True)
    for name, (_, text) in SERVICES.items():
        how = ROUTER if name == "router" else CLIENT
        sub = services.add_parser(
            name,
            parents=[common_options(2)],
            help=text,
            description=described(
                text,
                f"{how} Prints one JSON line when ready, a health line every few seconds, stops on SIGTERM.",
            ),
        )
        sub.add_argument(
            "--health-file",
            metavar="FILE",
            help="also write each health line to FILE (for `dynqos health FILE`, e.g. a Kubernetes probe)",
        )
        metrics_options(sub)
        sub.set_defaults(handler=run_edge)
    add_serve(services)

    onboard = commands.add_parser(
        "onboard",
        parents=[common_options(1)],
        description=ONBOARD,
        help="the drone's daemon: MAVLink to the FC, uplink to the edge, supervisor, fallback PID",
    )
    onboard.add_argument(
        "action",
        nargs="?",
        choices=["check"],
        help="check: the preflight (FC, signing, camera, router on both flows, QoS, systemd unit), one "
        "line per item, exit 0 only if all pass; nothing is armed or sent (docs/onboard.md)",
    )
    onboard.add_argument("--takeoff", action="store_true", help="arm, take off and start offloading")
    onboard.add_argument(
        "--measure-s",
        type=float,
        default=MEASURE_S,
        metavar="S",
        help=f"check: count the FC's rates and the camera's frames over S seconds "
        f"({MEASURE_S_RANGE[0]:g}..{MEASURE_S_RANGE[1]:g}, default %(default)g)",
    )
    metrics_options(onboard)
    onboard.set_defaults(handler=run_onboard)


MEASURE_S = 2.0  # the preflight counts rates over this long: 40 Hz asked, one message either way is 1 Hz
MEASURE_S_RANGE = (0.5, 60.0)
MATH_THREADS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_math_threads(threads: int, environ: MutableMapping[str, str]) -> None:
    """[mpc] math_threads for the BLAS and OpenMP under numpy: read once, when numpy loads, so set
    before any service module is imported (a variable the user set wins)."""
    for name in MATH_THREADS_VARIABLES:
        environ.setdefault(name, str(threads))


def run_edge(args: argparse.Namespace, config: Config) -> int:
    limit_math_threads(config.mpc.math_threads, os.environ)
    # The service's module is imported first: a missing extra is said before any network is opened.
    service = importlib.import_module(SERVICES[args.edge_command][0])
    config, health_file = with_metrics(args, config), path_or_none(args.health_file)
    declared = getattr(service, "SERVICE", None)
    if declared is not None:  # a service declared as a task (the MPC, the detector): served as any task
        from dynqos.edge import tasks

        code: int = tasks.run(declared, config, health_file=health_file)
        return code
    code = service.run(config, health_file=health_file)
    return code


SERVE = (
    "Serves a task of your own (docs/offload.md): TARGET names its dynqos.offload.Edge (a function) or "
    "Service (a core on the edge runtime), as MODULE:ATTR (a module on the Python path or in this "
    "folder) or path/to/file.py:ATTR; `dynqos edge mpc` is `serve dynqos.edge.mpc.service:SERVICE`. "
    "An Edge's handler runs on a "
    "worker thread; a call that raises, hangs, returns junk or answers past its budget is counted and "
    "said once, and the drone flies the task's fallback. Replicas of one task share the drones. "
    f"{CLIENT} Prints one JSON line when ready, a health line every few seconds, stops on SIGTERM."
)


def add_serve(services: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    text = "serve your own offloaded task: dynqos edge serve MODULE:ATTR"
    sub = services.add_parser("serve", parents=[common_options(2)], help=text, description=SERVE)
    sub.add_argument(
        "target", metavar="TARGET", help="the task's Edge or Service: MODULE:ATTR or path/file.py:ATTR"
    )
    sub.add_argument(
        "--replica-id",
        default="",
        metavar="ID",
        help="this replica's name among the task's replicas (default: <host>-<pid>)",
    )
    sub.add_argument("--health-file", metavar="FILE", help="also write each health line to FILE")
    metrics_options(sub)
    sub.set_defaults(handler=run_serve)


def run_serve(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.keys import check_replica_id
    from dynqos.common.tasks import Edge, Service, load

    limit_math_threads(config.mpc.math_threads, os.environ)
    declared = load(args.target, (Edge, Service))  # a module that fails to import: one line, exit 2
    if args.replica_id:
        try:
            check_replica_id(args.replica_id, "--replica-id")
        except ValueError as exc:
            raise ConfigError("--replica-id", str(exc)) from None
    from dynqos.edge import tasks

    code: int = tasks.run(
        declared,
        with_metrics(args, config),
        health_file=path_or_none(args.health_file),
        replica=args.replica_id,
    )
    return code


def run_onboard(args: argparse.Namespace, config: Config) -> int:
    from dynqos.onboard import daemon

    if args.action == "check":
        from dynqos.onboard import check

        low, high = MEASURE_S_RANGE
        if not low <= args.measure_s <= high:
            raise ConfigError("--measure-s", f"must be in {low:g}..{high:g} s, got {args.measure_s:g}")
        return check.run(config, args.measure_s)
    config = with_metrics(args, config)
    camera = None
    if config.onboard.camera == "sim" and config.onboard.camera_fps > 0:
        from dynqos.sim.vehicle.camera import SimCamera

        camera = SimCamera.for_drone(config)  # the simulator's camera, handed to the drone
    return daemon.run(config, takeoff=True if args.takeoff else None, camera=camera)
