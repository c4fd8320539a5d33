"""The `dynqos` command: one console script, subcommands for each job.

Every subcommand takes `--config FILE` and `--set KEY=VALUE`. Bad input (a missing file, a bad
value, an unknown key, an unreachable endpoint) ends with one line on stderr and exit code 2,
never a traceback.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from dynqos import __version__
from dynqos.common.config import Config, environment_overrides, load_config, to_toml
from dynqos.common.errors import DynqosError

log = logging.getLogger("dynqos")

Handler = Callable[[argparse.Namespace, Config], int]

EXIT_USAGE = 2
# Optional dependencies by the extra that brings them (pyproject.toml): a drone has none of them.
EXTRA_OF_MODULE = {
    "osqp": "edge",
    "scipy": "edge",
    "aiohttp": "edge",
    "matplotlib": "demo",
    "jsonschema": "demo",
}
MAX_INSTANCE = 254  # MAVLink system ids are 1..255


COMMON_LEVELS = 3  # dynqos [options] COMMAND [options] ACTION [options]: the common options at each level


def _common_options(level: int, *, settings: bool = True) -> argparse.ArgumentParser:
    """The common options of one level of subcommand, each stored under its own name per level.

    argparse copies a subcommand's defaults over its parent's values, so a single `--set` or `--config`
    given before the subcommand would be silently lost; with one name per level none is lost and `main`
    joins them (`_join_common_options`).
    """
    common = argparse.ArgumentParser(add_help=False)
    group = common.add_argument_group("common options (accepted before or after any subcommand)")
    if settings:
        _settings_options(group, level)
    group.add_argument(
        "--log-level",
        dest=f"log_level_{level}",
        choices=["debug", "info", "warning", "error"],
        help="logging verbosity (default: info)",
    )
    return common


def _settings_options(group: argparse._ArgumentGroup, level: int) -> None:
    group.add_argument(
        "--config",
        metavar="FILE",
        dest=f"config_{level}",
        help="TOML config file (default: built-in defaults)",
    )
    group.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        dest=f"overrides_{level}",
        help="override one setting, e.g. --set supervisor.th_lat=0.6 (repeatable; wins over the "
        "environment's DYNQOS_<SECTION>__<KEY> and the config file)",
    )


def _join_common_options(args: argparse.Namespace) -> None:
    """args.config, args.overrides and args.log_level from every level they were given at."""
    configs = [getattr(args, f"config_{n}", None) for n in range(COMMON_LEVELS)]
    given = list(dict.fromkeys(c for c in configs if c))
    if len(given) > 1:
        raise DynqosError(f"two config files given ({' and '.join(given)}); pass one")
    args.config = given[0] if given else None
    args.overrides = [o for n in range(COMMON_LEVELS) for o in getattr(args, f"overrides_{n}", None) or []]
    levels = [getattr(args, f"log_level_{n}", None) for n in range(COMMON_LEVELS)]
    args.log_level = next((lvl for lvl in reversed(levels) if lvl), "info")  # the innermost one given


def _cmd_config_show(args: argparse.Namespace, config: Config) -> int:
    for variable, setting in args.environment:
        sys.stdout.write(f"# from the environment: {variable} -> {setting}\n")
    sys.stdout.write(to_toml(config))
    return 0


def _cmd_config_zenoh(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.transport import Role, nested, session_settings

    settings = session_settings(config.zenoh, Role(args.role), check_files=False)
    use = (
        "zenohd -c FILE runs a router with the same endpoints, TLS and access control"
        if args.role == "router"
        else "zenoh.Config.from_file(FILE) opens the same session from any zenoh binding"
    )
    header = (
        f"// zenoh config of a dynqos {args.role} session, from `dynqos config zenoh --role {args.role}`.\n"
        f"// JSON is valid JSON5: {use}.\n"
    )
    sys.stdout.write(header + json.dumps(nested(settings), indent=2) + "\n")
    return 0


def _cmd_version(args: argparse.Namespace, config: Config) -> int:
    print(f"dynqos {__version__}")
    return 0


def _cmd_sim_cell(args: argparse.Namespace, config: Config) -> int:
    import asyncio
    from pathlib import Path

    from dynqos.sim.cell import print_ready, run_cell

    if args.duration is not None and args.duration <= 0:
        raise DynqosError(f"--duration must be > 0, got {args.duration}")
    from dynqos.common.camara import read_secret

    bearers = config.cell.bearer_list(config.zenoh, config.drone.id)
    out_dir = Path(args.out) if args.out else None
    camara = config.qos.camara
    devices = {uav: device.as_api() for uav, device in camara.devices.items()}
    secret = read_secret(camara.client_secret_file) if config.cell.qod_auth else ""
    if config.cell.qod_auth and not (camara.client_id and secret):
        raise DynqosError("[cell] qod_auth = true needs [qos.camara] client_id and client_secret_file")
    from dynqos.common.metrics import ProcessMetrics

    metrics = ProcessMetrics("cell", _with_metrics_options(args, config).metrics)
    metrics.start()
    try:
        asyncio.run(
            run_cell(
                config.cell, bearers, out_dir=out_dir, duration_s=args.duration, ready=print_ready,
                qod_devices=devices, qod_client=(camara.client_id, secret), metrics=metrics,
            )
        )  # fmt: skip
    finally:
        metrics.stop()
    return 0


def _cmd_sim_vehicle(args: argparse.Namespace, config: Config) -> int:
    import json
    import signal

    from dynqos.sim.vehicle import Link, MavlinkVehicle
    from dynqos.sim.vehicle_model import VehicleModel
    from dynqos.sim.world import default_world, load_world

    v = config.vehicle
    world_file = args.world if args.world is not None else v.world_file
    world = load_world(world_file) if world_file else default_world()
    lockstep = v.lockstep if args.clock is None else args.clock == "lockstep"
    speed = v.speed if args.speed is None else args.speed
    if not 0.01 <= speed <= 100:
        raise DynqosError(f"--speed must be in 0.01..100, got {speed}")
    if args.duration is not None and args.duration <= 0:
        raise DynqosError(f"--duration must be > 0, got {args.duration}")
    n = args.instance
    if not 0 <= n <= MAX_INSTANCE:
        raise DynqosError(f"--instance must be in 0..{MAX_INSTANCE}, got {n}")

    def plus_n(port: int) -> int:  # PX4 SITL's multi-vehicle ports; 0 (any free port) stays 0
        if port and port + n > 65535:
            raise DynqosError(f"--instance {n}: port {port} + {n} is past 65535")
        return port + n if port else 0

    model = VehicleModel(v)
    links = [
        Link("offboard", (v.host, plus_n(v.offboard_bind_port)), (v.host, plus_n(v.offboard_remote_port))),
        Link("gcs", (v.host, plus_n(v.gcs_bind_port)), (v.host, v.gcs_remote_port)),  # one GCS sees all
    ]
    vehicle = MavlinkVehicle(model, links, speed=speed, lockstep=lockstep, world=world, system_id=n + 1)
    try:
        vehicle.open()
    except OSError as exc:
        raise DynqosError(f"cannot bind the vehicle's MAVLink ports on {v.host}: {exc.strerror}") from None

    def stop(*_: object) -> None:
        vehicle.stopped = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    info = {
        "ready": True,
        "instance": n,
        "system_id": n + 1,
        "links": {link.name: {"bind": link.bind[1], "remote": link.remote[1]} for link in links},
        "clock": "lockstep" if lockstep else "realtime",
        "world": world_file or "default",
    }
    print(json.dumps(info), flush=True)
    try:
        vehicle.run(duration_s=args.duration)
    finally:
        vehicle.close()
        log.info("vehicle stopped: %s", vehicle.counters)
    return 0


def _ready_line(name: str) -> None:
    print(json.dumps({"ready": True, "service": name}), flush=True)


def _cmd_edge(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.metrics import ProcessMetrics
    from dynqos.common.transport import Role, open_bus

    name = args.edge_command
    config = _with_metrics_options(args, config)
    metrics = ProcessMetrics(name, config.metrics)
    if name == "router":
        from dynqos.edge.router import run_router

        metrics.start()
        try:
            run_router(
                config, ready=lambda: _ready_line("router"), health_file=_health_path(args), metrics=metrics
            )
        finally:
            metrics.stop()
        return 0
    worker_class, register = _edge_worker(name)  # imported first: a missing extra is said before any network
    if name == "qos":
        from dynqos.edge.qos_agent import preflight

        preflight(config)  # the operator settings, before any network is opened
    bus = open_bus(config.zenoh, Role.EDGE)
    try:
        worker = worker_class(config, bus)
        lifecycle = worker.service  # signals, health file and stop event of this process
        lifecycle.health_file = _health_path(args)
        lifecycle.beat = metrics.health.beat
        register(worker, metrics)
        metrics.start()
        if name == "qos":
            worker.run(ready=lambda: _ready_line("qos"))
            return 0
        lifecycle.install_signal_handlers()
        lifecycle.write_health("ready")
        _ready_line(name)
        worker.run()
    finally:
        metrics.stop()
        bus.close()
    return 0


def _with_metrics_options(args: argparse.Namespace, config: Config) -> Config:
    """--metrics-port and --metrics-host over [metrics] port and host."""
    import dataclasses

    from dynqos.common.config import MetricsConfig

    port = config.metrics.port if args.metrics_port is None else args.metrics_port
    host = args.metrics_host or config.metrics.host
    try:
        metrics = MetricsConfig(port=port, host=host, stale_after_s=config.metrics.stale_after_s)
    except DynqosError as exc:
        raise DynqosError(f"--metrics-port/--metrics-host: {exc}") from None
    return dataclasses.replace(config, metrics=metrics)


def _edge_worker(name: str) -> tuple[Any, Any]:
    """The service's class and the function that registers its metrics."""
    from dynqos.edge import metrics

    if name == "mpc":
        from dynqos.edge.mpc_service import MpcService

        return MpcService, metrics.mpc
    if name == "planner":
        from dynqos.edge.planner_service import PlannerService

        return PlannerService, metrics.planner
    if name == "qos":
        from dynqos.edge.qos_agent import QosAgent

        return QosAgent, metrics.qos
    from dynqos.edge.detector_service import DetectorService

    return DetectorService, metrics.detector


def _health_path(args: argparse.Namespace) -> Path | None:
    return Path(args.health_file) if args.health_file else None


def _cmd_health(args: argparse.Namespace, config: Config) -> int:
    from dynqos.edge.service import check_health

    if not 0 < args.max_age <= 3600:
        raise DynqosError(f"--max-age must be in (0, 3600] s, got {args.max_age}")
    print(check_health(Path(args.health_path), args.max_age))
    return 0


def _cmd_bench(args: argparse.Namespace, config: Config) -> int:
    from dynqos.bench.suite import run_suite

    run_suite(args.names, smoke=args.smoke, repeat=args.repeat, out=Path(args.out))
    return 0


def _cmd_certs(args: argparse.Namespace, config: Config) -> int:
    from dynqos.common.certs import make_dev_pki
    from dynqos.common.errors import KeyExprError

    if not args.drones:
        raise DynqosError("give at least one --drone ID")
    try:
        issued = make_dev_pki(
            Path(args.out), args.drones, args.router_hosts, days=args.days, ca_days=args.ca_days,
            force=args.force,
        )  # fmt: skip
    except KeyExprError as exc:
        raise DynqosError(f"--drone: {exc}") from None
    for name, pair in issued.items():
        print(f"{name}: {pair.cert} {pair.key}{' (kept)' if pair.kept else ''}")
    print(f"ca: {Path(args.out) / 'ca.pem'}")
    return 0


def _cmd_onboard(args: argparse.Namespace, config: Config) -> int:
    import signal

    from dynqos.common.metrics import ProcessMetrics
    from dynqos.onboard.daemon import OnboardDaemon

    config = _with_metrics_options(args, config)
    daemon = OnboardDaemon(config, takeoff=True if args.takeoff else None)
    metrics = ProcessMetrics("onboard", config.metrics)

    def stop(signum: int, _frame: object) -> None:
        log.info("onboard: %s received, stopping", signal.Signals(signum).name)
        daemon.stop.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        daemon.open()
        daemon.expose(metrics)
        metrics.start()
        _ready_line("onboard")
        daemon.run()
    finally:
        metrics.stop()
        daemon.close()
    return 0


def _cmd_observe(args: argparse.Namespace, config: Config) -> int:
    """`dynqos view` and `dynqos record`: one observer, a Foxglove server and/or an MCAP sink."""
    import signal

    from dynqos.observe import OBSERVER_NICE, Observer, open_recording, start_viewer
    from dynqos.sim.world import default_world, load_world

    os.nice(OBSERVER_NICE)  # below the control path on a shared machine: watching must not slow the loop
    world = load_world(args.world) if args.world else default_world()
    observer = Observer(config, world, uav=args.uav, camera=not args.no_camera)
    record = Path(args.out) if args.command == "record" else (Path(args.record) if args.record else None)
    writer = open_recording(observer, record, scenario=args.scenario) if record else None
    server = start_viewer(observer, args.host, args.port) if args.command == "view" else None

    def stop(signum: int, _frame: object) -> None:
        log.info("%s: %s received, stopping", args.command, signal.Signals(signum).name)
        observer.stop.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    try:
        observer.open()
        info: dict[str, Any] = {"ready": True, "service": args.command, "keys": observer.keys}
        if server is not None:
            info["port"] = server.port
            log.info(
                "view: Foxglove WebSocket on ws://%s:%d (open it in the Foxglove app)", args.host, server.port
            )
        if record is not None:
            info["out"] = str(record)
        print(json.dumps(info), flush=True)
        observer.run()
    finally:
        observer.close()
        if writer is not None:
            writer.close()  # the MCAP's summary and footer: a complete file
        if server is not None:
            server.stop()
        log.info("%s: stopped; %s", args.command, observer.summary())
    return 0


def _cmd_demo(args: argparse.Namespace, config: Config) -> int:
    from pathlib import Path

    from dynqos.demo import default_out_dir, run_demo
    from dynqos.profile import DEFAULT_PROFILE, load_profile
    from dynqos.scenario import DEFAULT_SCENARIOS, load_scenario

    if args.duration is not None and not 5 <= args.duration <= 3600:
        raise DynqosError(f"--duration must be in 5..3600 s, got {args.duration}")
    if args.scale is not None and not 0.01 <= args.scale <= 1000:
        raise DynqosError(f"--scale must be in 0.01..1000, got {args.scale}")
    out = Path(args.out) if args.out else default_out_dir()
    scenarios = [load_scenario(args.scenario_file)] if getattr(args, "scenario_file", None) else None
    names = getattr(args, "scenario", None) or list(DEFAULT_SCENARIOS)
    profiles = [load_profile(name) for name in (args.profile or [DEFAULT_PROFILE])]
    result = run_demo(
        names, out, duration_s=args.duration, scale=args.scale, seed=args.seed, scenarios=scenarios,
        profiles=profiles, repeat=args.repeat, metrics_port=args.metrics_port,
    )  # fmt: skip
    print(f"report: {out / 'report.md'}")
    for s in result["scenarios"]:
        print(_demo_line(s))
    return 0 if result["ok"] else 1


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise DynqosError(f"{option} takes numbers separated by commas, got {text!r}") from None
    if not values or any(v <= 0 for v in values):
        raise DynqosError(f"{option} takes positive numbers separated by commas, got {text!r}")
    return values


def _cmd_sensitivity(args: argparse.Namespace, config: Config) -> int:
    from pathlib import Path

    from dynqos.demo import default_out_dir
    from dynqos.sensitivity import MAX_REPEAT, run_sensitivity

    if not 5 <= args.duration <= 3600:
        raise DynqosError(f"--duration must be in 5..3600 s, got {args.duration}")
    if not 1 <= args.repeat <= MAX_REPEAT:
        raise DynqosError(f"--repeat must be in 1..{MAX_REPEAT}, got {args.repeat}")
    out = Path(args.out) if args.out else default_out_dir()
    out.mkdir(parents=True, exist_ok=True)
    result = run_sensitivity(
        out, weights=_floats(args.weights, "--weights"), loads_mbps=_floats(args.loads, "--loads"),
        duration_s=args.duration, seed=args.seed, repeat=args.repeat,
    )  # fmt: skip
    print(f"report: {out / 'sensitivity.md'}")
    return 0 if result["ok"] else 1


def _demo_line(s: dict[str, Any]) -> str:
    from dynqos.figures import figure
    from dynqos.scenario import run_id

    name = run_id(s["scenario"], s.get("profile", "dynqos"))
    if s.get("fleet"):
        from dynqos.demo import headline

        return f"  {name:<13} ok={s['ok']!s:<5} {headline(s)}"
    loaded = figure(s, "rtt_ms.loaded.mean")
    return (
        f"  {name:<13} ok={s['ok']!s:<5} RTT baseline {figure(s, 'rtt_ms.baseline.mean')} ms"
        + (f", loaded {loaded} ms" if loaded != "-" else "")
        + f", offered {figure(s, 'uav_offered_mbps')}, admitted {figure(s, 'uav_admitted_mbps')}"
        + f", delivered {figure(s, 'uav_delivered_mbps')} Mbit/s"
    )


def _how_it_connects(service: str) -> str:
    if service == "router":
        return (
            "Listens on [zenoh] router_listen_host (loopback by default), one port per flow; with tls = true "
            "it takes only mutual-TLS sessions and applies the access control of [zenoh] acl_drones."
        )
    return "Connects to the router at [zenoh] edge_host:default_port as a client."


def _metrics_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--metrics-port",
        type=int,
        metavar="PORT",
        help="serve Prometheus metrics on http://HOST:PORT/metrics and a probe on /healthz "
        "([metrics] port; default 0 = off)",
    )
    parser.add_argument(
        "--metrics-host",
        metavar="HOST",
        help="address the metrics listen on ([metrics] host; default 127.0.0.1)",
    )


def build_parser() -> argparse.ArgumentParser:  # noqa: PLR0915 (declarations: one per option)
    parser = argparse.ArgumentParser(
        prog="dynqos",
        description=(
            "Offload a drone's MPC controller, circle detector and mission planner to edge servers over "
            "Eclipse Zenoh, and keep real-time constraints when the 5G cell is loaded by switching QoS "
            "flows, throttling the camera or falling back to an onboard PID."
        ),
        epilog="Run 'dynqos COMMAND --help' for the options of one command. Every setting can also be "
        "given by an environment variable DYNQOS_<SECTION>__<KEY> (e.g. DYNQOS_DRONE__ID=uav7); the "
        "config file < the environment < --set.",
        parents=[_common_options(0)],
    )
    parser.add_argument("--version", action="version", version=f"dynqos {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    config_cmd = commands.add_parser("config", help="inspect configuration", parents=[_common_options(1)])
    config_sub = config_cmd.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = config_sub.add_parser(
        "show",
        parents=[_common_options(2)],
        help="print the effective config (defaults + file + --set) as TOML",
        description="Print the effective configuration: built-in defaults, then FILE, then --set overrides.",
    )
    show.add_argument("file", nargs="?", metavar="FILE", help="config file (same as --config FILE)")
    show.set_defaults(handler=_cmd_config_show)
    zenoh_show = config_sub.add_parser(
        "zenoh",
        parents=[_common_options(2)],
        help="print the zenoh config (JSON5) a router, edge or drone session opens with",
        description="Print the zenoh settings dynqos derives from [zenoh] for one role: endpoints with their "
        "priority ranges, TLS files and, for the router, the access-control policy from acl_drones. Use it "
        "to run the official zenohd with the same setup (zenohd -c FILE) or to see what a session does.",
    )
    zenoh_show.add_argument("file", nargs="?", metavar="FILE", help="config file (same as --config FILE)")
    zenoh_show.add_argument(
        "--role", choices=["router", "edge", "drone"], default="router", help="whose session (default router)"
    )
    zenoh_show.set_defaults(handler=_cmd_config_zenoh)

    sim_cmd = commands.add_parser(
        "sim",
        help="simulators: the emulated 5G cell, and a simulated quadrotor with its camera behind a MAVLink "
        "flight controller",
        parents=[_common_options(1)],
    )
    sim_sub = sim_cmd.add_subparsers(dest="sim_command", metavar="SIMULATOR", required=True)
    cell = sim_sub.add_parser(
        "cell",
        parents=[_common_options(2)],
        help="run the 5G cell emulator between the drone and the edge router",
        description=(
            "A user-space 5G uplink: one TCP listener per bearer (QoS flow) forwarding to an edge router "
            "port, a UE buffer per bearer, a resource-fair scheduler with relative priority weights every "
            "TTI, virtual background users, base delay and jitter, and timeline events. Configured by the "
            "[cell] table of the config file (see docs/cell.md). Prints one JSON line with the bearer "
            "ports when ready; stops on SIGINT/SIGTERM or after --duration."
        ),
    )
    cell.add_argument(
        "--duration", type=float, metavar="S", help="stop after S seconds (default: run until stopped)"
    )
    cell.add_argument("--out", metavar="DIR", help="write per-interval records to DIR/cell.csv")
    _metrics_options(cell)
    cell.set_defaults(handler=_cmd_sim_cell)

    vehicle = sim_sub.add_parser(
        "vehicle",
        parents=[_common_options(2)],
        help="run the simulated quadrotor that speaks MAVLink like PX4 SITL",
        description=(
            "A rigid-body quadrotor with a PX4-like flight controller (arming, takeoff, hold, land, offboard "
            "with PX4's custom modes and offboard-loss failsafe) speaking MAVLink 2 over UDP: the offboard "
            "link binds [vehicle] offboard_bind_port (14580) and sends to offboard_remote_port (14540); "
            "the ground-station link binds 18570 and sends to 14550. Prints one JSON line when ready. "
            "Contacts with the world's obstacles are logged and counted."
        ),
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
    vehicle.set_defaults(handler=_cmd_sim_vehicle)

    edge_cmd = commands.add_parser(
        "edge", help="edge services: router, mpc, planner, detector, qos", parents=[_common_options(1)]
    )
    edge_sub = edge_cmd.add_subparsers(dest="edge_command", metavar="SERVICE", required=True)
    for name, text in (
        ("router", "the zenoh router, listening on the default-flow (7447) and priority-flow (7448) ports"),
        (
            "mpc",
            "the MPC position controller: one OSQP controller per drone, answering each State with a Command",
        ),
        ("planner", "the mission planner: publishes each drone's reference trajectory ([planner] config)"),
        (
            "detector",
            "the circle detector: acks every camera frame, detects circles in RGB, locates them with depth",
        ),
        (
            "qos",
            "the QoS agent: turns the drones' requests for priority into what the network needs ([qos] "
            "backend: links, or camara for CAMARA Quality-on-Demand sessions; docs/qos.md)",
        ),
    ):
        sub = edge_sub.add_parser(
            name,
            parents=[_common_options(2)],
            help=text,
            description=text[0].upper() + text[1:] + ". " + _how_it_connects(name) + " Prints one JSON "
            "line when ready, a health line every few seconds, stops on SIGTERM.",
        )
        sub.add_argument(
            "--health-file",
            metavar="FILE",
            help="also write each health line to FILE (for `dynqos health FILE`, e.g. a Kubernetes probe)",
        )
        _metrics_options(sub)
        sub.set_defaults(handler=_cmd_edge)

    onboard = commands.add_parser(
        "onboard",
        parents=[_common_options(1)],
        help="the drone's daemon: MAVLink to the FC, uplink to the edge, supervisor, fallback PID",
        description=(
            "Connects to the flight controller ([onboard] mavlink_url, default udpin:127.0.0.1:14540 like "
            "PX4 SITL's offboard link) and to the edge router on two flows, streams state and camera, flies "
            "the edge's commands or the fallback PID, and runs the QoS supervisor. It never arms by itself: "
            "--takeoff arms, takes off to [onboard] takeoff_alt_m and starts offloading. SIGTERM: hold (or "
            "land) and exit."
        ),
    )
    onboard.add_argument("--takeoff", action="store_true", help="arm, take off and start offloading")
    _metrics_options(onboard)
    onboard.set_defaults(handler=_cmd_onboard)

    for name, text in (
        ("demo", "run the paper's scenarios end to end on this machine and write a report"),
        ("run", "run one scenario file (a TOML [scenario] table; copy one from dynqos/scenarios/)"),
    ):
        sub = commands.add_parser(
            name,
            parents=[_common_options(1, settings=False)],
            help=text,
            description=text[0].upper()
            + text[1:]
            + ". Starts the router, cell emulator, simulator, planner, MPC, "
            "detector and onboard daemon as processes, flies, records, stops everything (also on Ctrl-C), "
            "and writes per scenario summary.json, states.csv, supervisor.csv, latency.csv, cell.csv, "
            "plots and logs, plus report.md (docs/demo.md).",
        )
        if name == "run":
            sub.add_argument("scenario_file", metavar="FILE", help="scenario file")
        else:
            sub.add_argument(
                "--scenario",
                action="append",
                metavar="NAME",
                help="baseline, bg-noqos, bg-dynqos, bg-staticqos (repeatable; default: these four), or "
                "bg-dynqos-hover, bg-dynqos-refused, capacity-drop, faults, soak",
            )
        sub.add_argument("--out", metavar="DIR", help="run folder (default: runs/<date-time>)")
        sub.add_argument(
            "--metrics-port",
            type=int,
            default=0,
            metavar="BASE",
            help="each service's Prometheus /metrics on BASE, BASE+1, ... while it flies; the map is in "
            "<scenario>/logs/metrics.json (default 0: off)",
        )
        sub.add_argument("--duration", type=float, metavar="S", help="recorded flight time per scenario")
        sub.add_argument("--scale", type=float, metavar="F", help="divide every rate by F (default 10)")
        sub.add_argument(
            "--seed", type=int, metavar="N", help="seed for the simulator, cell jitter and supervisor"
        )
        sub.add_argument(
            "--repeat",
            type=int,
            default=1,
            metavar="N",
            help="run each scenario N times with seeds S, S+1, ... (S: --seed, else the scenario's); "
            "figures become mean [95%% interval] (default 1)",
        )
        sub.add_argument(
            "--profile",
            action="append",
            metavar="NAME",
            help="dynqos (the default), paper (the paper's supervisor on a cell with its 27.3 ms RTT), "
            "no-rate-adaptation, or a profile file (dynqos/profiles/*.toml shows the format); repeatable: "
            "each scenario flies under each profile, side by side in report.md",
        )
        sub.set_defaults(handler=_cmd_demo)

    sensitivity = commands.add_parser(
        "sensitivity",
        parents=[_common_options(1, settings=False)],
        help="fly bg-staticqos once per priority weight and background load: where priority stops helping",
        description="Fly the bg-staticqos scenario (priority flow all along) once per priority weight and "
        "background load, and write summary.json, sensitivity.md and sensitivity.png: the drone's loaded "
        "C&C RTT and delivered rate against the weight, one line per load.",
    )
    sensitivity.add_argument("--weights", default="1,2,4,8", metavar="W,W,...", help="priority weights")
    sensitivity.add_argument("--loads", default="40,80,120", metavar="M,M,...", help="background Mbit/s")
    sensitivity.add_argument("--duration", type=float, default=20.0, metavar="S", help="seconds per point")
    sensitivity.add_argument("--seed", type=int, default=0, metavar="N", help="seed of every point")
    sensitivity.add_argument(
        "--repeat", type=int, default=1, metavar="N",
        help="fly each point N times with seeds S, S+1, ... (S: --seed); figures become mean [95%% interval] "
        "and the plot draws the intervals (default 1)",
    )  # fmt: skip
    sensitivity.add_argument("--out", metavar="DIR", help="output folder (default: runs/<date-time>)")
    sensitivity.set_defaults(handler=_cmd_sensitivity)

    bench = commands.add_parser(
        "bench",
        parents=[_common_options(1, settings=False)],
        help="run the benchmarks (what the runtime costs, beside its floor) and write bench-results.json",
        description="Runs each benchmark against its floor and target (all by default: supervisor_step, "
        "mpc_step, control_loop, fleet_zenoh, edge_per_drone, onboard_camera, vehicle_sim, cell_forward, "
        "supervisor_reaction), prints one verdict line each, and writes bench-results.json (every "
        "figure) and bench-results.md (the tables) into --out. Benchmarks report; the exit code is 0 "
        "whatever the verdicts. docs/benchmarks.md explains each one.",
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
    bench.set_defaults(handler=_cmd_bench)

    health = commands.add_parser(
        "health",
        parents=[_common_options(1, settings=False)],
        help="check a service's health file (exit 0 if fresh): for Kubernetes exec probes",
        description="Prints the last health line written by a service started with --health-file FILE "
        "and exits 0 if it is at most --max-age seconds old; otherwise says why and exits 2.",
    )
    health.add_argument("health_path", metavar="FILE", help="the service's --health-file")
    health.add_argument(
        "--max-age", type=float, default=15.0, metavar="S", help="oldest acceptable line (default 15 s)"
    )
    health.set_defaults(handler=_cmd_health)

    certs = commands.add_parser(
        "certs",
        parents=[_common_options(1, settings=False)],
        help="make a development CA and mTLS certificates: the router, each edge service, each drone",
        description="Writes into --out (made 0700): ca.pem and ca-key.pem (kept and reused if present), "
        "router.pem (server and client auth; names: localhost, 127.0.0.1 and each --router-host), one "
        "identity per edge service (edge-mpc, edge-planner, edge-detector, edge-qos: each may touch only "
        "its own keys) and <id>.pem per --drone (CN = drone id, matched by the router's access control), "
        "each with its <name>-key.pem (mode 0600, written through a new file, never through a link). "
        "Pairs that exist and are still valid are kept unless --force, so adding a drone re-issues "
        "nothing else. No certificate outlives the CA. For production use your own PKI with the same "
        "common names; rotation and revocation: docs/security.md.",
    )
    certs.add_argument("--out", metavar="DIR", required=True, help="folder for the PEM files")
    certs.add_argument(
        "--drone", metavar="ID", action="append", default=[], dest="drones", help="a drone id (repeatable)"
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
    certs.set_defaults(handler=_cmd_certs)

    for name, text in (
        (
            "view",
            "serve the drones live to the Foxglove app over its WebSocket protocol (docs/observability.md)",
        ),
        ("record", "record the drones to an MCAP file that Foxglove and the mcap tools open"),
    ):
        observe = commands.add_parser(
            name,
            parents=[_common_options(1)],
            help=text,
            description=text[0].upper() + text[1:] + ": poses, the reference path, the world's obstacles and "
            "the risk zone as a 3D scene, the RGB camera with its detections, the supervisor's status, the "
            "QoS grants and decisions, and the supervisor's transitions as log lines. Connects to the router "
            "at [zenoh] edge_host as an edge client. Stops on SIGTERM or Ctrl-C, closing the file whole.",
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
        observe.set_defaults(handler=_cmd_observe)

    version = commands.add_parser(
        "version", help="print the version", parents=[_common_options(1, settings=False)]
    )
    version.set_defaults(handler=_cmd_version)
    return parser


BUILDS_ITS_OWN_CONFIG: dict[Handler, str] = {
    _cmd_demo: "each scenario builds its own config; change settings with --profile FILE",
    _cmd_sensitivity: "each point builds its own config from the scenario",
    _cmd_bench: "each benchmark sets up what it measures",
    _cmd_health: "it reads only the health file",
    _cmd_certs: "it reads only its own options",
    _cmd_version: "it reads nothing",
}  # commands that read no settings: a --config or --set given to them would be silently ignored


def _config_path(args: argparse.Namespace) -> str | None:
    file_arg = getattr(args, "file", None)
    if file_arg and args.config and file_arg != args.config:
        raise DynqosError(f"two config files given ({file_arg} and --config {args.config}); pass one")
    path: str | None = file_arg or args.config
    return path


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _join_common_options(args)
    except DynqosError as exc:
        parser.error(str(exc))  # exit 2 with the usage line
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    handler: Handler = args.handler
    if handler in BUILDS_ITS_OWN_CONFIG and (args.config or args.overrides):
        parser.error(f"'{args.command}' takes no --config or --set: {BUILDS_ITS_OWN_CONFIG[handler]}")
    try:
        args.environment = environment_overrides(os.environ)
        config = load_config(_config_path(args), args.overrides, environment=args.environment)
        return handler(args, config)
    except DynqosError as exc:
        print(f"dynqos: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:  # a role installed without the extra this command needs
        top = (exc.name or "").split(".")[0]
        if top not in EXTRA_OF_MODULE:
            return _internal_error(exc)
        extra = EXTRA_OF_MODULE[top]
        print(
            f"dynqos: error: '{args.command}' needs {top}, which comes with the {extra} extra: "
            f"pip install 'dynqos[{extra}]'",
            file=sys.stderr,
        )
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("dynqos: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        return _internal_error(exc)


def _internal_error(exc: Exception) -> int:
    """A bug, not bad input: say so in one line, the traceback at debug level."""
    log.debug("internal error", exc_info=exc)
    print(
        f"dynqos: internal error: {type(exc).__name__}: {exc} (run with --log-level debug)", file=sys.stderr
    )
    return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
