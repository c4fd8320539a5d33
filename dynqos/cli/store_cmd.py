"""`dynqos store RUN DEST`: a run folder thinned for committing (docs/development.md, "Storing a run")."""

from __future__ import annotations

import argparse
from pathlib import Path

from dynqos.cli.options import Commands, common_options
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError

STORE = (
    "Copies a run folder (from dynqos demo, run or sensitivity) into DEST, thinned to what is worth "
    "committing: every JSON file whose value a kept summary in the same folder or above it already holds "
    "is left out (each seed's summary is an entry of its scenario's, which is an entry of the run's), "
    "JSON is written compact, plots get a 16-colour palette, each scenario keeps only its first seed's "
    "plots and config (a later seed's differs in its seed and ports), and "
    "the raw series (CSV files, logs) are left out unless --keep-series. No figure changes. DEST/STORED.md "
    "names every file left out and, for a summary, the entry of a kept file that holds it "
    '(docs/development.md, "Storing a run").'
)


def add(commands: Commands) -> None:
    store = commands.add_parser(
        "store",
        parents=[common_options(1, settings=False)],
        help="copy a run folder thinned for committing (no repeated summaries, compact JSON, small plots)",
        description=STORE,
    )
    store.add_argument("run", metavar="RUN", help="the run folder, e.g. runs/<date-time>")
    store.add_argument("dest", metavar="DEST", help="where to write it (must not exist yet)")
    store.add_argument(
        "--keep-series", action="store_true", help="keep the CSV series and logs as well (default: left out)"
    )
    store.set_defaults(handler=run_store, own_config="it reads only the run folder")


def run_store(args: argparse.Namespace, config: Config) -> int:
    from dynqos.reports.store import store

    try:
        result = store(Path(args.run), Path(args.dest), keep_series=args.keep_series)
    except OSError as exc:
        raise DynqosError(f"store: {exc.strerror or exc} ({exc.filename or args.dest})") from None
    print(f"{args.dest}: {result.describe()}; see {Path(args.dest) / 'STORED.md'}")
    return 0
