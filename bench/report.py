"""What every benchmark shares: when and where it ran, and how its result is written."""

from __future__ import annotations

import argparse
import json
import platform
import statistics
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from dynqos.experiment.machine import own_machine, usable_core_count


def provenance() -> dict[str, Any]:
    """When, and on what: the cores this process may use and, in a container, its CPU quota (a
    benchmark's figures are the quota's, not the host's; dynqos/experiment/cgroup.py)."""
    quota = own_machine()[1]
    cores = f"{usable_core_count()} cores" + (f" (a CPU quota of {quota.cores:.2f})" if quota else "")
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {cores}, python {platform.python_version()}",
    }


def micros(durations_ns: list[int]) -> dict[str, float]:
    """Timed durations (ns) as their median, 99th percentile and mean in microseconds."""
    ordered = sorted(durations_ns)
    return {
        "median_us": statistics.median(ordered) / 1e3,
        "p99_us": ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))] / 1e3,
        "mean_us": statistics.fmean(ordered) / 1e3,
    }


def emit(result: dict[str, Any], table: str, out: Path | None, verdict: str) -> int:
    """Print the JSON result, its Markdown table and the one-line verdict against the target; also
    write the JSON (verdict included) to `out` if given. Always 0: a benchmark reports, it does not
    fail a build."""
    result["verdict"] = verdict
    text = json.dumps(result, indent=2)
    if out is not None:
        out.write_text(text + "\n")
    print(text)
    print(table)
    print(f"verdict: {verdict}")
    return 0


def pct(share: float | None) -> str:
    """A share (0..1) as a percentage with one decimal, "-" for none."""
    return "-" if share is None else f"{100 * share:.1f}%"


def judged(met: bool, text: str) -> str:
    """'meets target: ...' or 'misses target: ...'."""
    return f"{'meets' if met else 'misses'} target: {text}"


def bench_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's command line: its docstring as help, and --out FILE for the JSON result."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, help="also write the JSON result to this file")
    return parser


def flight_args(
    doc: str | None, argv: list[str] | None, *, seeds_from: int, duration_s: float, quick_s: float
) -> tuple[int, float, Path | None]:
    """The command line of a benchmark that flies a scenario once per seed: (runs, recorded seconds per
    run, --out); `--quick` (smoke mode) is one run of `quick_s`."""
    parser = bench_parser(doc)
    last = "N" if seeds_from == 1 else "N-1"
    parser.add_argument("--seeds", type=int, default=3, help=f"runs, seeds {seeds_from}..{last} (default 3)")
    parser.add_argument(
        "--duration",
        type=float,
        default=duration_s,
        help=f"recorded flight per run (default {duration_s:g} s)",
    )
    parser.add_argument("--quick", action="store_true", help=f"smoke mode: one {quick_s:g} s run")
    args = parser.parse_args(argv)
    if not 1 <= args.seeds <= 20 or not 10 <= args.duration <= 600:
        parser.error("--seeds must be in 1..20 and --duration in 10..600 s")
    return (1, quick_s, args.out) if args.quick else (args.seeds, args.duration, args.out)
