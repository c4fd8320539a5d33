"""Profiles (the paper's parameters beside dynqos's) and repeated runs reported with 95% intervals."""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.config import SupervisorConfig, ZenohConfig
from dynqos.common.errors import ConfigError
from dynqos.experiment.profile import DEFAULT_PROFILE, load_profile
from dynqos.plan.scenario import builtin_scenario, scenario_config
from dynqos.reports.aggregate import aggregate, interval, repeated_summary
from dynqos.reports.figures import figure
from dynqos.reports.markdown import write_report
from tests.procs import DYNQOS


def test_the_interval_is_students_t_over_the_runs() -> None:
    result = interval([1.0, 2.0, 3.0])
    assert result["mean"] == pytest.approx(2.0)
    half = 4.302652729911275 * 1.0 / 3**0.5  # t(0.975, 2) * s / sqrt(n)
    assert (result["ci95_low"], result["ci95_high"]) == pytest.approx((2.0 - half, 2.0 + half))
    assert interval([5.0]) == {"mean": 5.0, "ci95_low": 5.0, "ci95_high": 5.0, "n": 1}


def test_aggregate_takes_every_figure_by_its_path_and_leaves_out_settings_and_missing_ones() -> None:
    runs: list[dict[str, Any]] = [
        {"seed": 0, "ok": True, "rtt_ms": {"loaded": {"mean": 10.0}}, "first_qos_switch_after_bg_s": 0.3},
        {"seed": 1, "ok": True, "rtt_ms": {"loaded": {"mean": 14.0}}, "first_qos_switch_after_bg_s": None},
    ]
    agg = aggregate(runs)
    assert agg["rtt_ms.loaded.mean"]["mean"] == pytest.approx(12.0)
    assert agg["rtt_ms.loaded.mean"]["n"] == 2
    assert agg["first_qos_switch_after_bg_s"]["n"] == 1  # the run without a switch is left out
    assert "seed" not in agg  # a setting...
    assert "ok" not in agg  # ...and a flag are not figures


def test_the_paper_profile_flies_the_papers_supervisor_on_a_cell_calibrated_to_its_rtt() -> None:
    paper = load_profile("paper")
    scenario = paper.apply(builtin_scenario("bg-dynqos"))
    assert scenario.run_id == "bg-dynqos@paper"
    assert scenario.base_delay_ms == 10.0
    sup = scenario.supervisor
    assert (sup.mu, sup.rho, sup.w, sup.window) == (
        (3.0, 5.0, 5.0),
        (61.0, 27.0, 3.0),
        (0.35, 0.65),
        (10, 50),
    )
    assert (sup.cc_fast_window, sup.probe_s, sup.recover_backoff) == (0, 0.0, 1.0)  # none of dynqos's own
    config = scenario_config(replace(scenario, seed=7), zenoh=ZenohConfig(), fc_port=1, gcs_port=2)
    assert config.supervisor.cc_fast_window == 0
    assert config.supervisor.seed == 7
    assert config.cell.base_delay_up_ms == 10.0


def test_the_default_profile_changes_nothing() -> None:
    scenario = builtin_scenario("bg-noqos")
    applied = load_profile(DEFAULT_PROFILE).apply(scenario)
    assert applied == scenario
    assert applied.supervisor == SupervisorConfig()
    assert applied.run_id == "bg-noqos"
    # A scenario's own supervisor settings survive a profile; a profile changes only what it names.
    own = replace(scenario, supervisor=SupervisorConfig(th_lat=0.6))
    assert load_profile(DEFAULT_PROFILE).apply(own).supervisor.th_lat == 0.6
    paper = load_profile("paper").apply(own).supervisor
    assert (paper.th_lat, paper.cc_fast_window) == (0.6, 0)


def test_bad_profiles_are_named_errors(tmp_path: Path) -> None:
    known = r"dynqos, network-aware, no-rate-adaptation, paper"
    with pytest.raises(ConfigError, match=rf"unknown profile 'nope'.*{known}"):
        load_profile("nope")
    bad = tmp_path / "bad.toml"
    bad.write_text('[profile]\nname = "bad"\n[supervisor]\nfast = 1\n')
    with pytest.raises(ConfigError, match=r"supervisor\.fast.*unknown key"):
        load_profile(str(bad))
    bad.write_text('[profile]\nname = "bad"\n[scenario]\nname = "other"\n')
    with pytest.raises(ConfigError, match="not their names"):
        load_profile(str(bad))
    bad.write_text('[profile]\nname = "bad"\n[scenario]\nscale = 0\n')
    with pytest.raises(ConfigError, match="scale"):
        load_profile(str(bad))
    with pytest.raises(ConfigError, match="not found"):
        load_profile(str(tmp_path / "missing.toml"))


def _summary(seed: int, rtt: float, profile: str = "dynqos", hl: float = 0.0) -> dict[str, Any]:
    stats = {"mean": rtt, "p50": rtt, "p95": rtt, "p99": rtt, "max": rtt, "n": 10}
    return {
        "scenario": "baseline", "profile": profile, "description": "d", "qos": "dynamic",
        "mission": "circle", "duration_s": 10.0, "scale": 10.0, "seed": seed, "bg_start_s": None,
        "bg_mbps": 0.0, "settle_s": 4.0, "uav_offered_mbps": 47.0, "uav_admitted_mbps": 48.0,
        "uav_delivered_mbps": 48.0, "bg_offered_mbps": 0.0, "bg_delivered_mbps": 0.0,
        "rtt_ms": {"baseline": stats, "loaded": None},
        "camera_latency_ms": {"baseline": stats, "loaded": None},
        "tracking_rmse_m": {"baseline": 0.03, "loaded": None}, "first_qos_switch_after_bg_s": None,
        "first_qos_switch_cause": None, "camera_fps": {"configured": 15.0, "baseline": 15.0, "loaded": None},
        "hl_fraction_baseline": hl, "fallback_entered": False, "setpoint_gap_max_ms": 25.0,
        "states_time_s": {"q1": 10.0}, "ok": True, "failure": "",
    }  # fmt: skip


def test_the_report_shows_intervals_for_repeats_and_says_what_the_papers_parameters_did(
    tmp_path: Path,
) -> None:
    repeated = repeated_summary([_summary(0, 18.0), _summary(1, 20.0), _summary(2, 19.0)])
    assert [run["seed"] for run in repeated["runs"]] == [0, 1, 2]
    assert figure(repeated, "rtt_ms.baseline.mean") == "19.0 [16.5, 21.5]"
    paper = _summary(0, 28.2, profile="paper", hl=1.0)
    write_report(tmp_path, [repeated, paper])
    report = (tmp_path / "report.md").read_text()
    assert "| baseline | dynqos | 3 | No QoS - No BG |" in report
    assert "19.0 [16.5, 21.5] / -" in report
    assert "The paper's parameters at the paper's baseline" in report
    assert "high latency in 100% of the unloaded flight" in report
    assert (tmp_path / "spread.png").stat().st_size > 1000


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--profile", "nope"], "unknown profile 'nope'"),
        (["--repeat", "0"], "--repeat: must be in 1..50"),
    ],
)
def test_demo_rejects_a_bad_profile_or_repeat_in_one_line(
    tmp_path: Path, args: list[str], message: str
) -> None:
    result = subprocess.run([DYNQOS, "demo", "--out", str(tmp_path / "run"), *args],
                            capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "run" / "summary.json").exists()


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(400)
def test_both_profiles_repeated_run_side_by_side(tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = subprocess.run(
        [DYNQOS, "demo", "--scenario", "baseline", "--profile", "dynqos", "--profile", "paper",
         "--repeat", "2", "--duration", "6", "--out", str(out)],
        capture_output=True, text=True, timeout=380, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    ours = json.loads((out / "baseline" / "summary.json").read_text())
    paper = json.loads((out / "baseline@paper" / "summary.json").read_text())
    for summary in (ours, paper):
        assert [run["seed"] for run in summary["runs"]] == [0, 1]
        assert (out / summary["scenario"]).exists()
        assert {"mean", "ci95_low", "ci95_high", "n"} <= set(summary["aggregate"]["rtt_ms.baseline.mean"])
    for seed in (0, 1):
        assert (out / "baseline@paper" / f"seed{seed}" / "summary.json").exists()
    # The calibration shows: the paper's cell puts the unloaded RTT near its 27.3 ms, ours well below.
    assert (
        paper["aggregate"]["rtt_ms.baseline.mean"]["mean"]
        > ours["aggregate"]["rtt_ms.baseline.mean"]["mean"] + 5
    )
    report = (out / "report.md").read_text()
    assert "| baseline | paper | 2 |" in report
    assert "The paper's parameters at the paper's baseline" in report


def test_repeated_faults_are_aggregated_by_their_place_and_reported_with_intervals(tmp_path: Path) -> None:
    def fault(rtt: float, states: dict[str, float], slowed: float | None, fallback: bool) -> dict[str, Any]:
        return {"kind": "capacity", "at_s": 15.0, "duration_s": 15.0, "fallback": fallback, "recovered": True,
                "rtt_ms_during": {"mean": rtt, "p95": 2 * rtt}, "states_s_during": states,
                "camera_slowed_after_s": slowed, "log": [], "notes": []}  # fmt: skip

    runs = [
        _summary(0, 18.0) | {"faults": [fault(140.0, {"q3": 3.0, "q6": 12.0}, 3.2, False)]},
        _summary(1, 19.0) | {"faults": [fault(160.0, {"q3": 3.0, "qA": 10.0}, None, True)]},
    ]
    repeated = repeated_summary(runs)
    agg = repeated["aggregate"]
    assert agg["faults.0.rtt_ms_during.mean"]["mean"] == pytest.approx(150.0)
    assert agg["faults.0.fallback_fraction"]["mean"] == pytest.approx(0.5)
    assert agg["faults.0.camera_slowed_after_s"]["n"] == 1  # the run where it never slowed is left out
    write_report(tmp_path, [repeated])
    report = (tmp_path / "report.md").read_text()
    assert "capacity at 15 s for 15 s: RTT while it lasted mean 150.0 [" in report
    assert "q6 6.0 [" in report  # a state one run never entered counts 0 s there, not a missing run
    assert "camera slowed in 1 of 2 runs, 3.20 s after it began; fallback in 1 of 2 runs" in report
