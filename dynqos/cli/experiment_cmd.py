"""`dynqos demo`, `dynqos run FILE` and `dynqos sensitivity`: the experiment, end to end on one machine."""

from __future__ import annotations

import argparse
from importlib import resources
from pathlib import Path
from typing import Any

from dynqos.cli.options import Commands, common_options, described
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError

DEFAULT_FOUR = ("baseline", "bg-noqos", "bg-dynqos", "bg-staticqos")  # the demo's default scenarios


def _builtin_names() -> list[str]:
    """The shipped scenarios' names, read without importing the experiment (the parser stays quick)."""
    files = resources.files("dynqos") / "scenarios"
    return sorted(p.name.removesuffix(".toml") for p in files.iterdir() if p.name.endswith(".toml"))


FLIES = (
    "Starts the router, cell emulator, simulator, planner, MPC, detector and onboard daemon as processes, "
    "flies, records, stops everything (also on Ctrl-C), and writes per scenario summary.json, states.csv, "
    "supervisor.csv, latency.csv, cell.csv, plots and logs, plus report.md (docs/demo.md)."
)
OWN_CONFIG = "each scenario builds its own config; change settings with --profile FILE"


def add(commands: Commands) -> None:
    for name, text in (
        ("demo", "run the paper's scenarios end to end on this machine and write a report"),
        ("run", "run one scenario file (a TOML [scenario] table; copy one from dynqos/scenarios/)"),
    ):
        sub = commands.add_parser(
            name, parents=[common_options(1, settings=False)], help=text, description=described(text, FLIES)
        )
        if name == "run":
            sub.add_argument("scenario_file", metavar="FILE", help="scenario file")
        else:
            sub.add_argument(
                "--scenario",
                action="append",
                metavar="NAME",
                help="baseline, bg-noqos, bg-dynqos, bg-staticqos (repeatable; default: these four), or "
                + ", ".join(n for n in _builtin_names() if n not in DEFAULT_FOUR),
            )
        _flight_options(sub)
        sub.set_defaults(handler=run_demo, own_config=OWN_CONFIG)

    sensitivity = commands.add_parser(
        "sensitivity",
        parents=[common_options(1, settings=False)],
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
        "--repeat",
        type=int,
        default=1,
        metavar="N",
        help="fly each point N times with seeds S, S+1, ... (S: --seed); figures become mean [95%% interval] "
        "and the plot draws the intervals (default 1)",
    )
    sensitivity.add_argument("--out", metavar="DIR", help="output folder (default: runs/<date-time>)")
    sensitivity.set_defaults(
        handler=run_sensitivity, own_config="each point builds its own config from the scenario"
    )


def _flight_options(sub: argparse.ArgumentParser) -> None:
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
        "--vehicle",
        choices=["sim", "px4"],
        help="who flies the drone: dynqos's simulated vehicle (sim, the scenario's default) or a real PX4 "
        "SITL, one instance per drone (px4; needs --px4-dir or [px4] dir, docs/px4.md)",
    )
    sub.add_argument(
        "--qos-backend",
        choices=["links", "camara", "nef"],
        help="how the network gives the priority flow its weight: a QoD session from the emulated "
        "operator (camara, the scenarios' default), a subscription from its emulated 5G core's NEF "
        "(nef, one drone), or a static policy for the priority port (links); docs/qos.md",
    )
    sub.add_argument(
        "--trace",
        metavar="FILE",
        help="the cell's uplink capacity replays this Mahimahi trace (one packet opportunity a line), "
        "rescaled to the scenario's [cell] trace_mean_mbps; the trace-none, trace-paper, trace-delay, "
        "trace-queue and trace-split scenarios need one (docs/camera.md)",
    )
    sub.add_argument(
        "--px4-dir",
        metavar="DIR",
        help="PX4's folder (bin/px4 and etc/, such as PX4's build/px4_sitl_default); default: [px4] dir, "
        "e.g. from DYNQOS_PX4__DIR",
    )
    sub.add_argument(
        "--profile",
        action="append",
        metavar="NAME",
        help="dynqos (the default), paper (the paper's supervisor on a cell with its 27.3 ms RTT), "
        "no-rate-adaptation, radio-aware, network-aware (with --qos-backend nef), or a profile file "
        "(dynqos/profiles/*.toml shows the format); repeatable: "
        "each scenario flies under each profile, side by side in report.md",
    )


def run_demo(args: argparse.Namespace, config: Config) -> int:
    from dynqos.experiment.demo import default_out_dir, run_demo
    from dynqos.experiment.profile import DEFAULT_PROFILE, load_profile
    from dynqos.plan.scenario import DEFAULT_SCENARIOS, load_scenario

    if args.duration is not None and not 5 <= args.duration <= 3600:
        raise DynqosError(f"--duration must be in 5..3600 s, got {args.duration}")
    if args.scale is not None and not 0.01 <= args.scale <= 1000:
        raise DynqosError(f"--scale must be in 0.01..1000, got {args.scale}")
    vehicle = _vehicle(args, config)
    out = Path(args.out) if args.out else default_out_dir()
    scenarios = [load_scenario(args.scenario_file)] if getattr(args, "scenario_file", None) else None
    names = getattr(args, "scenario", None) or list(DEFAULT_SCENARIOS)
    profiles = [load_profile(name) for name in (args.profile or [DEFAULT_PROFILE])]
    result = run_demo(
        names,
        out,
        duration_s=args.duration,
        scale=args.scale,
        seed=args.seed,
        scenarios=scenarios,
        profiles=profiles,
        repeat=args.repeat,
        metrics_port=args.metrics_port,
        vehicle=vehicle,
        qos_backend=getattr(args, "qos_backend", None),
        trace=_trace(args.trace),
    )
    print(f"report: {out / 'report.md'}")
    for s in result["scenarios"]:
        print(demo_line(s))
    return 0 if result["ok"] else 1


def _vehicle(args: argparse.Namespace, config: Config) -> dict[str, Any]:
    """The scenario changes that --vehicle and --px4-dir ask for (a PX4 folder checked now, not mid-run)."""
    px4_dir = args.px4_dir or config.px4.dir
    if args.vehicle != "px4":
        return {"vehicle": args.vehicle} if args.vehicle else {}
    from dynqos.sim.vehicle.px4_sitl import px4_folder

    return {"vehicle": "px4", "px4_dir": str(px4_folder(px4_dir))}


def _trace(path: str | None) -> str | None:
    """--trace's file as an absolute path, read now: a trace that cannot fly is an error before any run."""
    if path is None:
        return None
    from dynqos.sim.network.traces import Trace, TraceError

    try:
        Trace.load(path)
    except TraceError as exc:
        raise DynqosError(f"--trace: {exc}") from None
    return str(Path(path).resolve())


def floats(text: str, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise DynqosError(f"{option} takes numbers separated by commas, got {text!r}") from None
    if not values or any(v <= 0 for v in values):
        raise DynqosError(f"{option} takes positive numbers separated by commas, got {text!r}")
    return values


def run_sensitivity(args: argparse.Namespace, config: Config) -> int:
    from dynqos.experiment.demo import default_out_dir
    from dynqos.experiment.sensitivity import MAX_REPEAT, run_sensitivity

    if not 5 <= args.duration <= 3600:
        raise DynqosError(f"--duration must be in 5..3600 s, got {args.duration}")
    if not 1 <= args.repeat <= MAX_REPEAT:
        raise DynqosError(f"--repeat must be in 1..{MAX_REPEAT}, got {args.repeat}")
    out = Path(args.out) if args.out else default_out_dir()
    out.mkdir(parents=True, exist_ok=True)
    result = run_sensitivity(
        out,
        weights=floats(args.weights, "--weights"),
        loads_mbps=floats(args.loads, "--loads"),
        duration_s=args.duration,
        seed=args.seed,
        repeat=args.repeat,
    )
    print(f"report: {out / 'sensitivity.md'}")
    return 0 if result["ok"] else 1


def demo_line(s: dict[str, Any]) -> str:
    from dynqos.plan.scenario import run_id
    from dynqos.reports.figures import figure

    name = run_id(s["scenario"], s.get("profile", "dynqos"))
    if s.get("fleet"):
        from dynqos.experiment.demo import headline

        return f"  {name:<13} ok={s['ok']!s:<5} {headline(s)}"
    loaded = figure(s, "rtt_ms.loaded.mean")
    return (
        f"  {name:<13} ok={s['ok']!s:<5} RTT baseline {figure(s, 'rtt_ms.baseline.mean')} ms"
        + (f", loaded {loaded} ms" if loaded != "-" else "")
        + f", offered {figure(s, 'uav_offered_mbps')}, admitted {figure(s, 'uav_admitted_mbps')}"
        + f", delivered {figure(s, 'uav_delivered_mbps')} Mbit/s"
    )
