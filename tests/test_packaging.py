"""A built wheel (not only the editable install) must import the mapped package folders."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.wheel import build_wheel

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.timeout(300)
def test_built_wheel_imports_every_component(tmp_path: Path) -> None:
    wheel = build_wheel(tmp_path)
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        archive.extractall(site)
    for module in ("dynqos/cli/main.py", "dynqos/common/messages.py", "dynqos/edge/qos/agent.py",
                   "dynqos/sim/vehicle/mavlink.py", "dynqos/sim/network/cell.py",
                   "dynqos/reports/summary.py", "dynqos/onboard/__init__.py",
                   "dynqos/edge/__init__.py", "dynqos/sim/__init__.py", "dynqos/py.typed",
                   "dynqos/bench/suite.py", "dynqos/bench/zenoh_echo.py", "dynqos/experiment/faults.py",
                   "dynqos/scenarios/faults.toml", "dynqos/scenarios/soak.toml",
                   "dynqos/scenarios/bg-dynqos-hover.toml", "dynqos/profiles/paper.toml",
                   "dynqos/profiles/dynqos.toml", "dynqos/profiles/no-rate-adaptation.toml",
                   "dynqos/scenarios/capacity-drop.toml"):  # fmt: skip
        assert module in names
    folders = {"dynqos": "dynqos", "common": "dynqos/common", "onboard": "dynqos/onboard",
               "edge": "dynqos/edge", "sim": "dynqos/sim", "bench": "dynqos/bench"}  # fmt: skip
    sources = {
        f"{inside}/{path.relative_to(ROOT / folder).as_posix()}"
        for folder, inside in folders.items()
        for path in (ROOT / folder).rglob("*.py")
    }
    assert sources - names == set()  # every module of every subpackage is in the wheel
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        "import dynqos.common.messages as m, dynqos.cli, dynqos.onboard, dynqos.edge, dynqos.sim;"
        "import dynqos.bench.suite, dynqos.common.certs, dynqos.experiment.faults, dynqos.experiment.profile;"
        "assert dynqos.experiment.profile.load_profile('paper').supervisor['cc_fast_window'] == 0;"
        "assert m.__file__.startswith(sys.argv[1]), m.__file__; print('ok')"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, str(site)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "ok"
