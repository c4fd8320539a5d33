"""Benchmarks run in smoke mode: they must work and report their fields; no timing is asserted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench import supervisor_step


def test_supervisor_step_bench_smoke(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "result.json"
    assert supervisor_step.main(["--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["steps"] == 2000
    for key in ("median_us", "p99_us", "mean_us"):
        assert result["step"][key] > 0
        assert result["floor"][key] > 0
    assert "| supervisor step |" in capsys.readouterr().out


def test_cell_forward_bench_smoke(tmp_path: Path) -> None:
    from bench import cell_forward

    out = tmp_path / "cell.json"
    assert cell_forward.main(["--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    for key in ("emulator", "bare_relay"):
        assert result[key]["cpu_share_of_one_core"] >= 0
        assert result[key]["delivered_mbps"] > 5


def test_vehicle_sim_bench_smoke(tmp_path: Path) -> None:
    from bench import vehicle_sim

    out = tmp_path / "sim.json"
    assert vehicle_sim.main(["--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["lockstep"]["sim_s_per_wall_s"] > 0
    assert result["camera"]["render_and_encode"]["mbps_at_30fps"] > 0


def test_mpc_bench_smoke(tmp_path: Path) -> None:
    from bench import mpc_step

    out = tmp_path / "mpc.json"
    assert mpc_step.main(["--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert [s["horizon"] for s in result["steps"]] == [20, 40]
    assert result["fleet"]["max_drones_at_20hz"] >= 0


def test_onboard_camera_bench_smoke(tmp_path: Path) -> None:
    from bench import onboard_camera

    out = tmp_path / "camera.json"
    assert onboard_camera.main(["--quick", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["frames_delivered"] == result["frames"] == 10
    assert result["mbps_at_30fps"] > 0
