"""The `dynqos` command: parse, load the settings, dispatch to the command's handler, and turn every
error into one line and an exit code.

Every subcommand takes `--config FILE` and `--set KEY=VALUE`. Bad input (a missing file, a bad value,
an unknown key, an unreachable endpoint) ends with one line on stderr and exit code 2, never a
traceback."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from dynqos import __version__
from dynqos.cli import config_cmd, edge_cmd, experiment_cmd, sim_cmd, store_cmd, tools_cmd
from dynqos.cli.options import Handler, common_options, join_common_options
from dynqos.common.config import environment_overrides, load_config
from dynqos.common.errors import DynqosError

log = logging.getLogger("dynqos")

EXIT_USAGE = 2
# Optional dependencies by the extra that brings them (pyproject.toml): a drone has none of them.
EXTRA_OF_MODULE = {
    "osqp": "edge",
    "scipy": "edge",
    "aiohttp": "edge",
    "matplotlib": "demo",
    "jsonschema": "demo",
    "rosbags": "ros2",
}


def build_parser() -> argparse.ArgumentParser:
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
        parents=[common_options(0)],
    )
    parser.add_argument("--version", action="version", version=f"dynqos {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for group in (config_cmd, sim_cmd, edge_cmd, experiment_cmd, store_cmd, tools_cmd):
        group.add(commands)
    return parser


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
        join_common_options(args)
    except DynqosError as exc:
        parser.error(str(exc))  # exit 2 with the usage line
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    handler: Handler = args.handler
    own_config = getattr(args, "own_config", None)  # a command that reads no settings would ignore them
    if own_config and (args.config or args.overrides):
        parser.error(f"'{args.command}' takes no --config or --set: {own_config}")
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
