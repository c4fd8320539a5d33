"""The options every command shares, and the pieces several command groups use."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TypeAlias

from dynqos.common.config import Config
from dynqos.common.errors import DynqosError

Handler = Callable[[argparse.Namespace, Config], int]
Commands: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"

COMMON_LEVELS = 3  # dynqos [options] COMMAND [options] ACTION [options]: the common options at each level


def common_options(level: int, *, settings: bool = True) -> argparse.ArgumentParser:
    """The common options of one level of subcommand, each stored under its own name per level.

    argparse copies a subcommand's defaults over its parent's values, so a single `--set` or `--config`
    given before the subcommand would be silently lost; with one name per level none is lost and `main`
    joins them (`join_common_options`).
    """
    common = argparse.ArgumentParser(add_help=False)
    group = common.add_argument_group("common options (accepted before or after any subcommand)")
    if settings:
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
    group.add_argument(
        "--log-level",
        dest=f"log_level_{level}",
        choices=["debug", "info", "warning", "error"],
        help="logging verbosity (default: info)",
    )
    return common


def join_common_options(args: argparse.Namespace) -> None:
    """args.config, args.overrides and args.log_level from every level they were given at."""
    configs = [getattr(args, f"config_{n}", None) for n in range(COMMON_LEVELS)]
    given = list(dict.fromkeys(c for c in configs if c))
    if len(given) > 1:
        raise DynqosError(f"two config files given ({' and '.join(given)}); pass one")
    args.config = given[0] if given else None
    args.overrides = [o for n in range(COMMON_LEVELS) for o in getattr(args, f"overrides_{n}", None) or []]
    levels = [getattr(args, f"log_level_{n}", None) for n in range(COMMON_LEVELS)]
    args.log_level = next((lvl for lvl in reversed(levels) if lvl), "info")  # the innermost one given


def metrics_options(parser: argparse.ArgumentParser) -> None:
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


def with_metrics(args: argparse.Namespace, config: Config) -> Config:
    """`config` with --metrics-port and --metrics-host over [metrics] port and host."""
    from dynqos.common.lifecycle import with_metrics_endpoint

    return with_metrics_endpoint(config, args.metrics_port, args.metrics_host)


def path_or_none(text: str | None) -> Path | None:
    return Path(text) if text else None


def described(text: str, more: str) -> str:
    """A subcommand's description: its one-line help as a sentence, then `more`."""
    return f"{text[0].upper()}{text[1:]}. {more}"
