"""Each role installs only what it runs: the drone's `dynqos[onboard]` has no solver and no plotting.

Slow: it builds the wheel and installs it with its dependencies into a fresh virtual environment (from
the package index, or pip's cache after the project's own install).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def _run(*cmd: str | Path, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """`cmd` from a folder outside the repository, whose dynqos/ would shadow the installed package."""
    return subprocess.run(
        [str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, check=False, cwd="/"
    )


def test_the_onboard_extra_runs_the_drone_without_matplotlib_scipy_or_osqp(tmp_path: Path) -> None:
    built = _run(
        sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", tmp_path, ROOT
    )
    assert built.returncode == 0, built.stderr
    (wheel,) = tmp_path.glob("dynqos-*.whl")
    venv = tmp_path / "venv"
    assert _run(sys.executable, "-m", "venv", venv).returncode == 0
    python = venv / "bin" / "python"
    installed = _run(python, "-m", "pip", "install", "-q", "--disable-pip-version-check", f"{wheel}[onboard]")
    assert installed.returncode == 0, installed.stderr[-3000:]

    solvers = ("matplotlib", "scipy", "osqp", "aiohttp")
    missing = _run(
        python, "-c", f"import importlib.util as u; print([m for m in {solvers} if u.find_spec(m)])"
    )
    assert missing.stdout.strip() == "[]", missing.stdout + missing.stderr
    dynqos = venv / "bin" / "dynqos"
    helped = _run(dynqos, "onboard", "--help", timeout=60)
    assert helped.returncode == 0, helped.stderr
    assert "--takeoff" in helped.stdout
    # The drone's modules import in full (the daemon, the MAVLink link, the camera, the supervisor).
    imported = _run(python, "-c", "import dynqos.onboard.daemon, dynqos.sim.vehicle; print('ok')", timeout=60)
    assert imported.stdout.strip() == "ok", imported.stderr
    # An edge service on a drone's install says which extra it needs, in one line, before any network.
    edge = _run(dynqos, "edge", "mpc", "--set", "zenoh.connect_timeout_s=0.5", timeout=60)
    assert edge.returncode == 2
    assert edge.stderr.strip() == (
        "dynqos: error: 'edge' needs osqp, which comes with the edge extra: pip install 'dynqos[edge]'"
    )
