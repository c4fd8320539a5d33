"""The `dynqos` command: one console script, subcommands for each job.

Every subcommand takes `--config FILE` and `--set KEY=VALUE`. Bad input (a missing file, a bad
value, an unknown key, an unreachable endpoint) ends with one line on stderr and exit code 2,
never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

from dynqos import __version__
from dynqos.common.config import Config, load_config, to_toml
from dynqos.common.errors import DynqosError

log = logging.getLogger("dynqos")

Handler = Callable[[argparse.Namespace, Config], int]

EXIT_USAGE = 2


def _common_options() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    group = common.add_argument_group("common options")
    group.add_argument("--config", metavar="FILE", help="TOML config file (default: built-in defaults)")
    group.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        dest="overrides",
        help="override one setting, e.g. --set supervisor.th_lat=0.6 (repeatable)",
    )
    group.add_argument(
        "--log-level",
        default="info",
        choices=["debug", "info", "warning", "error"],
        help="logging verbosity (default: info)",
    )
    return common


def _cmd_config_show(args: argparse.Namespace, config: Config) -> int:
    sys.stdout.write(to_toml(config))
    return 0


def _cmd_version(args: argparse.Namespace, config: Config) -> int:
    print(f"dynqos {__version__}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    common = _common_options()
    parser = argparse.ArgumentParser(
        prog="dynqos",
        description=(
            "Offload a drone's MPC controller, circle detector and mission planner to edge servers over "
            "Eclipse Zenoh, and keep real-time constraints when the 5G cell is loaded by switching QoS "
            "flows, throttling the camera or falling back to an onboard PID."
        ),
        epilog="Run 'dynqos COMMAND --help' for the options of one command.",
    )
    parser.add_argument("--version", action="version", version=f"dynqos {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    config_cmd = commands.add_parser("config", help="inspect configuration", parents=[common])
    config_sub = config_cmd.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = config_sub.add_parser(
        "show",
        parents=[common],
        help="print the effective config (defaults + file + --set) as TOML",
        description="Print the effective configuration: built-in defaults, then FILE, then --set overrides.",
    )
    show.add_argument("file", nargs="?", metavar="FILE", help="config file (same as --config FILE)")
    show.set_defaults(handler=_cmd_config_show)

    version = commands.add_parser("version", help="print the version", parents=[common])
    version.set_defaults(handler=_cmd_version)
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
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    handler: Handler = args.handler
    try:
        config = load_config(_config_path(args), args.overrides)
        return handler(args, config)
    except DynqosError as exc:
        print(f"dynqos: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("dynqos: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
