"""The camera on a traced uplink (docs/camera.md): the trace-none, trace-paper, trace-delay, trace-queue
and trace-split scenarios, `dynqos demo --trace FILE`, and the report's figures for a flight whose
capacity replays a trace."""

from __future__ import annotations

import json
import re
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest

from dynqos.common.errors import ConfigError
from dynqos.experiment.demo import run_demo
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import builtin_scenario
from dynqos.reports.summary import cell_rates
from dynqos.reports.uplink import traced_lines
from tests.procs import DYNQOS

TRACES = ("trace-none", "trace-paper", "trace-delay", "trace-queue", "trace-split")


def test_the_scenarios_fly_the_same_trace_and_differ_in_how_the_camera_is_slowed() -> None:
    none, paper, delay, queue, split = (builtin_scenario(name) for name in TRACES)
    for s in (none, paper, delay, queue, split):
        assert s.config["cell"]["trace_mean_mbps"] == 80.0
        assert s.bg_start_s < 0  # the trace is the only thing that changes
    assert (none.supervisor.rate_factor, none.supervisor.min_rate_factor) == (1.0, 1.0)
    assert paper.supervisor == delay.supervisor == queue.supervisor  # its factor stays the ceiling
    assert paper.supervisor.camera_flow == "state"
    assert split.supervisor == replace(queue.supervisor, camera_flow="default")  # the camera pinned...
    assert (split.qos, queue.qos) == ("priority", "dynamic")  # ...the state on the priority flow
    assert split.config == queue.config
    assert paper.supervisor.rate_factor < 1.0
    assert delay.config["onboard"] == {"camera_rate_control": "delay"}  # GCC, the default controller
    assert queue.config["onboard"] == {"camera_rate_control": "delay", "camera_rate_controller": "queue"}
    assert "onboard" not in none.config
    assert "onboard" not in paper.config


def test_a_trace_scenario_without_a_trace_is_refused_before_any_run(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with pytest.raises(ConfigError, match="--trace FILE"):
        run_demo(["baseline", "trace-delay"], out, duration_s=None, scale=None, seed=None)
    assert not out.exists()  # nothing flew, not even the scenario before it


def test_a_trace_file_that_is_not_a_trace_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.up"
    bad.write_text("12\nseven\n")
    for trace, says in ((bad, "not a Mahimahi trace"), (tmp_path / "missing.up", "cannot read trace")):
        result = subprocess.run(
            [DYNQOS, "demo", "--scenario", "trace-none", "--trace", str(trace), "--out", str(tmp_path / "o")],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert result.returncode == 2, result.stderr
        assert says in result.stderr
        assert "Traceback" not in result.stderr
    assert not (tmp_path / "o").exists()


def _cell(now_s: float, capacity_bits: float, delivered_bytes: int, dropped_bytes: int) -> dict[str, object]:
    bearer = {"offered_bytes": delivered_bytes + dropped_bytes, "delivered_bytes": delivered_bytes}
    return {
        "now_ns": round(now_s * 1e9),
        "capacity_bits": capacity_bits,
        "bearers": {"uav1-default": {**bearer, "dropped_bytes": dropped_bytes}},
        "background": {"bg": {"offered_bits": 0, "delivered_bits": 0}},
    }


def test_the_share_carried_is_what_reached_the_edge_of_what_the_trace_could_carry() -> None:
    rec = Recording()
    rec.cell = [_cell(0.0, 0.0, 0, 0), _cell(2.0, 8e6, 500_000, 25_000)]  # 4 Mbit/s; 2 of it delivered
    rates = cell_rates(rec.cell, 0, round(2e9), scale=10.0)
    assert rates["uplink_capacity_mbps"] == pytest.approx(40.0)
    assert rates["uav_delivered_mbps"] == pytest.approx(20.0)
    assert rates["uav_dropped_mbps"] == pytest.approx(1.0)
    rec.cell = [{k: v for k, v in c.items() if k != "capacity_bits"} for c in rec.cell]  # an older cell
    assert cell_rates(rec.cell, 0, round(2e9), scale=10.0)["uplink_capacity_mbps"] is None


def test_the_report_tables_the_traced_flights_only() -> None:
    traced = {"scenario": "trace-delay", "ok": True, "uplink_trace": "ATT.up", "uplink_share": 0.61,
              "camera_latency_ms": {"baseline": {"p50": 120.0, "p95": 900.0}}}  # fmt: skip
    plain = {"scenario": "baseline", "ok": True, "uplink_trace": None}
    lines = traced_lines([plain, traced])
    rows = [line for line in lines if line.startswith("| trace")]
    assert len(rows) == 1
    assert "| ATT.up | 1 |" in rows[0]
    assert "| 0.61 |" in rows[0]
    assert "| 900 |" in rows[0]
    assert traced_lines([plain]) == []


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(300)
@pytest.mark.parametrize("scenario", ["trace-delay", "trace-queue"])
def test_a_flight_on_a_trace_counts_its_capacity_and_the_controller_reads_the_acks(
    tmp_path: Path, scenario: str
) -> None:
    """A synthetic trace with a one-second period: 0.8 s at one packet a millisecond, then 0.2 s at
    five. Rescaled to the scenario's 80 Mbit/s, any whole number of periods averages exactly that. Each
    controller (GCC, the queue-delay target) reads the detector's acks and sets the camera's rate."""
    trace = tmp_path / "steps.up"
    stamps = [*range(1, 801), *(t for t in range(801, 1001) for _ in range(5))]
    trace.write_text("\n".join(map(str, stamps)) + "\n")
    out = tmp_path / "run"
    result = subprocess.run(
        [DYNQOS, "demo", "--scenario", scenario, "--trace", str(trace), "--duration", "10",
         "--out", str(out)],
        capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    summary = json.loads((out / scenario / "summary.json").read_text())
    assert summary["uplink_trace"] == "steps.up", result.stderr[-2000:]
    assert summary["uplink_capacity_mbps"] == pytest.approx(80.0, rel=0.1)
    assert 0 < summary["uav_delivered_mbps"] <= 1.02 * summary["uplink_capacity_mbps"]
    assert summary["uplink_share"] == pytest.approx(
        summary["uav_delivered_mbps"] / summary["uplink_capacity_mbps"]
    )
    health = (out / scenario / "logs" / "onboard.log").read_text()
    read = [int(n) for n in re.findall(r"camera_acks_read=(\d+)", health)]
    refused = [int(n) for n in re.findall(r"camera_acks_refused=(\d+)", health)]
    assert read
    assert read[-1] > 10 * 10
    assert refused[-1] == 0
    targets = re.findall(r"camera_target_mbps=(\S+)", health)
    assert targets
    assert targets[-1] != "-"  # the controller answered a target
    report = (out / "report.md").read_text()
    assert "## The camera on a traced uplink" in report
    assert f"| {scenario} | steps.up | 1 |" in report
