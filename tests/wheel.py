"""The project's wheel as a fresh clone builds it: from a copy of the source without build/ and
*.egg-info/, since setuptools reuses an in-tree build/lib and the egg-info's SOURCES.txt, whose stale
entries would hide a subpackage missing from pyproject's package list."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LEFT_OUT = (".git", ".venv", "build", "*.egg-info", "results", "__pycache__", ".*cache", "runs")


def build_wheel(out: Path) -> Path:
    source = out / "source"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(*LEFT_OUT))
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out),
         str(source)],
        capture_output=True, text=True, timeout=240, check=False, cwd="/",
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = out.glob("dynqos-*.whl")
    return wheel
