"""`dynqos sensitivity`: its table and plot from the points, and its errors for bad input."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from dynqos.experiment.sensitivity import _plot, _repeated_point, markdown
from dynqos.plan.scenario import builtin_scenario
from tests.procs import DYNQOS


def _point(weight: float, load: float, rtt: float, delivered: float) -> dict[str, object]:
    return {
        "priority_weight": weight, "bg_mbps": load, "share_of_full_cell": weight / (weight + 1),
        "rtt_baseline_mean_ms": 19.0, "rtt_loaded_mean_ms": rtt, "rtt_loaded_p95_ms": rtt * 1.3,
        "uav_offered_mbps": 45.0, "uav_admitted_mbps": 47.0, "uav_delivered_mbps": delivered,
        "bg_delivered_mbps": 81.3 - delivered, "ok": True,
    }  # fmt: skip


def test_the_table_and_plot_show_every_point(tmp_path: Path) -> None:
    points = [_point(1, 80, 240.0, 40.6), _point(4, 80, 19.5, 47.0)]
    text = markdown(
        {"scenario": "bg-staticqos", "duration_s": 20.0, "seed": 0, "scale": 10.0, "points": points}
    )
    assert "| 1 | 0.50 | 80 | 19.0 / 240.0 | 312.0 | 45.0 / 40.6 | 40.7 |" in text
    assert "| 4 | 0.80 | 80 |" in text
    _plot(tmp_path, points)  # type: ignore[arg-type]
    assert (tmp_path / "sensitivity.png").stat().st_size > 1000


def test_repeated_points_report_the_mean_and_interval_of_each_figure(tmp_path: Path) -> None:
    runs = [_point(2, 80, rtt, 47.0) | {"seed": k} for k, rtt in enumerate((30.0, 34.0, 32.0))]
    point = _repeated_point(runs)
    assert point["rtt_loaded_mean_ms"] == pytest.approx(32.0)
    half = 4.302652729911275 * 2.0 / 3**0.5  # t(0.975, 2) * s / sqrt(n)
    agg = point["ci95"]["rtt_loaded_mean_ms"]
    assert (agg["ci95_low"], agg["ci95_high"]) == pytest.approx((32.0 - half, 32.0 + half))
    assert point["seeds"] == [0, 1, 2]
    assert point["runs"] == runs
    text = markdown({"scenario": "bg-staticqos", "duration_s": 20.0, "seed": 0, "repeat": 3, "scale": 10.0,
                     "points": [point]})  # fmt: skip
    assert "3 runs per point (seeds 0-2)" in text
    assert f"| 19.0 [19.0, 19.0] / 32.0 [{32.0 - half:.1f}, {32.0 + half:.1f}] |" in text
    _plot(tmp_path, [point])
    assert (tmp_path / "sensitivity.png").stat().st_size > 1000


def test_the_scenario_carries_its_priority_weight_into_the_cell() -> None:
    from dataclasses import replace

    from dynqos.common.config import ZenohConfig
    from dynqos.plan.scenario import scenario_config

    scenario = replace(builtin_scenario("bg-staticqos"), priority_weight=2.0)
    config = scenario_config(scenario, zenoh=ZenohConfig(), fc_port=1, gcs_port=2)
    weights = {b.name: b.weight for b in config.cell.bearer_list(config.zenoh, "uav1")}
    assert weights == {"uav1-default": 1.0, "uav1-priority": 2.0}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--weights", "1,x"], "--weights takes numbers"),
        (["--loads", "0"], "--loads takes positive"),
        (["--repeat", "0"], "--repeat must be in 1..20"),
    ],
)
def test_bad_sweeps_are_one_line_errors(tmp_path: Path, args: list[str], message: str) -> None:
    result = subprocess.run([DYNQOS, "sensitivity", "--out", str(tmp_path), *args],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
