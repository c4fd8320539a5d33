"""`dynqos config show` and `dynqos config zenoh`: what the settings are, and what zenoh gets of them."""

from __future__ import annotations

import argparse
import json
import sys

from dynqos.cli.options import Commands, common_options
from dynqos.common.config import Config, to_toml


def add(commands: Commands) -> None:
    config_cmd = commands.add_parser("config", help="inspect configuration", parents=[common_options(1)])
    actions = config_cmd.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    show = actions.add_parser(
        "show",
        parents=[common_options(2)],
        help="print the effective config (defaults + file + --set) as TOML",
        description="Print the effective configuration: built-in defaults, then FILE, then --set overrides.",
    )
    show.add_argument("file", nargs="?", metavar="FILE", help="config file (same as --config FILE)")
    show.set_defaults(handler=show_config)
    zenoh = actions.add_parser(
        "zenoh",
        parents=[common_options(2)],
        help="print the zenoh config (JSON5) a router, edge or drone session opens with",
        description="Print the zenoh settings dynqos derives from [zenoh] for one role: endpoints with their "
        "priority ranges, TLS files and, for the router, the access-control policy from acl_drones. Use it "
        "to run the official zenohd with the same setup (zenohd -c FILE) or to see what a session does.",
    )
    zenoh.add_argument("file", nargs="?", metavar="FILE", help="config file (same as --config FILE)")
    zenoh.add_argument(
        "--role", choices=["router", "edge", "drone"], default="router", help="whose session (default router)"
    )
    zenoh.set_defaults(handler=show_zenoh)


def show_config(args: argparse.Namespace, config: Config) -> int:
    for variable, setting in args.environment:
        sys.stdout.write(f"# from the environment: {variable} -> {setting}\n")
    sys.stdout.write(to_toml(config))
    return 0


def show_zenoh(args: argparse.Namespace, config: Config) -> int:
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
