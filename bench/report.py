"""What every benchmark shares: when and where it ran, and how its result is written."""

from __future__ import annotations

import argparse
import json
import os
import platform
from datetime import datetime, timezone
from pathlib import Path
from typing import Any


def provenance() -> dict[str, Any]:
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}",
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


def judged(met: bool, text: str) -> str:
    """'meets target: ...' or 'misses target: ...'."""
    return f"{'meets' if met else 'misses'} target: {text}"


def bench_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's command line: its docstring as help, and --out FILE for the JSON result."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, help="also write the JSON result to this file")
    return parser
