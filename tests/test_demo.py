"""`dynqos demo` end to end (short and scaled down) and the summary.json contract."""

from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import pytest

from dynqos.common.config import ZenohConfig, load_config
from dynqos.plan.cells import with_cell
from dynqos.plan.scenario import builtin_scenario, scenario_config, write_config
from tests.procs import DYNQOS

# The command watchdog ([supervisor] watchdog_s): a setpoint stall that long would be a control outage.
# How steady the 50 Hz setpoints are is a speed target: bench/supervisor_reaction.py, docs/benchmarks.md.
T_WD_MS = 1000 * load_config(None).supervisor.watchdog_s

KEYS = {
    "scenario",
    "duration_s",
    "scale",
    "bg_start_s",
    "uav_offered_mbps",
    "uav_admitted_mbps",
    "uav_delivered_mbps",
    "bg_offered_mbps",
    "bg_delivered_mbps",
    "rtt_ms",
    "camera_latency_ms",
    "tracking_rmse_m",
    "states_time_s",
    "transitions",
    "first_qos_switch_after_bg_s",
    "first_qos_switch_cause",
    "camera_fps",
    "fallback_entered",
    "setpoint_gap_max_ms",
    "ok",
}
STATS = {"mean", "p50", "p95", "p99", "max"}


def _check_the_flight_log(path: Path, scenario: str, summary: dict[str, object]) -> None:
    """The demo's MCAP opens with the mcap reader like any recording: closed, schemas, metadata."""
    reader_module = pytest.importorskip("mcap.reader")
    with path.open("rb") as stream:
        reader = reader_module.make_reader(stream)
        assert reader.get_summary() is not None
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        counts: dict[str, int] = {}
        for schema, channel, _ in reader.iter_messages():
            assert schema is not None
            assert schema.data
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert metadata["dynqos"]["scenario"] == scenario
    assert "[supervisor]" in metadata["dynqos.config"]["toml"]
    assert counts["/uav1/pose"] > 15 * 10  # a state per MPC period (20 Hz) over a flight of over 10 s
    assert counts["/uav1/status"] > 10
    assert "/uav1/camera/rgb" not in counts  # the demo records without images (a small run folder)


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)
def test_short_demo_writes_the_contract(tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = subprocess.run(
        [
            DYNQOS,
            "demo",
            "--scenario",
            "baseline",
            "--scenario",
            "bg-staticqos",
            "--duration",
            "14",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=540,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    top = json.loads((out / "summary.json").read_text())
    assert top["ok"] is True
    assert [s["scenario"] for s in top["scenarios"]] == ["baseline", "bg-staticqos"]
    for name in ("baseline", "bg-staticqos"):
        summary = json.loads((out / name / "summary.json").read_text())
        assert set(summary) >= KEYS, KEYS - set(summary)
        assert summary["ok"] is True
        assert set(summary["rtt_ms"]["baseline"]) >= STATS
        assert set(summary["states_time_s"]) == {"q1", "q2", "q3", "q4", "q5", "q6", "qA"}
        for artefact in (
            "overview.png",
            "supervisor.png",
            "states.csv",
            "supervisor.csv",
            "latency.csv",
            "cell.csv",
            "logs",
            "flight.mcap",
        ):
            assert (out / name / artefact).exists(), artefact
        _check_the_flight_log(out / name / "flight.mcap", name, summary)
        assert summary["setpoint_gap_max_ms"] < T_WD_MS  # no stall a watchdog would call an outage
        # the QoD path: the emulated operator is left with no session once every process has stopped
        assert summary["qos_network"]["backend"] == "camara"
        assert summary["qos_network"]["sessions"]["open_at_end"] == 0, summary["qos_network"]
    baseline = json.loads((out / "baseline" / "summary.json").read_text())
    assert baseline["rtt_ms"]["baseline"]["mean"] < 27  # below rho2 with margin
    with (out / "baseline" / "latency.csv").open() as f:
        rtts = [float(row["ms"]) for row in csv.DictReader(f) if row["kind"] == "rtt"]
    assert len(rtts) >= 10 * baseline["duration_s"]  # every RTT (20 Hz), not only the last per status
    assert baseline["rtt_ms"]["baseline"]["n"] >= 10 * (baseline["duration_s"] - 5)  # after settling
    assert baseline["tracking_rmse_m"]["baseline"] < 0.15
    loaded = json.loads((out / "bg-staticqos" / "summary.json").read_text())
    assert loaded["bg_start_s"] is not None
    assert (
        loaded["uav_delivered_mbps"] >= 0.95 * loaded["uav_admitted_mbps"]
    )  # the priority flow keeps its rate
    network = loaded["qos_network"]
    assert network["sessions"]["created"] >= 1
    assert network["sessions"]["deleted"] == network["sessions"]["created"]
    assert network["grant_at_end"] == "available"
    assert loaded["rtt_ms"]["loaded"]["mean"] < 1.2 * loaded["rtt_ms"]["baseline"]["mean"]
    report = (out / "report.md").read_text()
    assert "Table II" in report
    assert "baseline/overview.png" in report
    assert "the baseline scenario (the same wind, no load) over the same spans" in report


def test_bad_scenario_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('[scenario]\nname = "x"\nduration_s = 1\n')
    result = subprocess.run(
        [DYNQOS, "run", str(path)], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"dynqos: error: {path}: scenario.duration_s: must be in 5..3600 s"
    ]
    unknown = subprocess.run(
        [DYNQOS, "demo", "--scenario", "nope"], capture_output=True, text=True, timeout=60, check=False
    )
    assert unknown.returncode == 2
    assert "unknown scenario 'nope'" in unknown.stderr


@pytest.mark.parametrize(
    "name",
    [
        "baseline",
        "bg-noqos",
        "bg-dynqos",
        "bg-staticqos",
        "faults",
        "trace-none",
        "trace-delay",
        "trace-queue",
        "trace-split",
    ],
)
def test_a_scenarios_config_is_written_and_read_back_unchanged(tmp_path: Path, name: str) -> None:
    """What the runner writes is exactly what every process reads: qos, camera size and pace, the
    cell's scaled buffer and the bearers' ports the cell reported all survive the round trip."""
    scenario = builtin_scenario(name)
    config = scenario_config(scenario, zenoh=ZenohConfig(default_port=7001, priority_port=7002),
                             fc_port=14601, gcs_port=14602)  # fmt: skip
    bearers = {"uav1-default": {"port": 17001}, "uav1-priority": {"port": 17002}}
    config = with_cell(config, {"bearers": bearers, "control_port": 17003}, sink_port=17004)
    path = tmp_path / "dynqos.toml"
    write_config(path, scenario, config)
    loaded = load_config(path)
    assert loaded == config
    assert loaded.onboard.qos == scenario.qos
    assert loaded.onboard.connect_priority == "127.0.0.1:17002"
    assert loaded.qos.camara.api_root == "http://127.0.0.1:17003/quality-on-demand/v1"
    assert loaded.qos.camara.sink_listen == "127.0.0.1:17004"
    assert loaded.cell.qod is (scenario.qos_backend == "camara")
    assert loaded.cell.ue_buffer_bytes == round(1_000_000 / scenario.scale)
    assert loaded.onboard.camera_pace_mbps == pytest.approx(scenario.camera_pace_mbps / scenario.scale)


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(400)
def test_an_operator_that_refuses_priority_leaves_the_drone_adapting_not_crashing(tmp_path: Path) -> None:
    """bg-dynqos-refused: the supervisor asks for priority under load and the emulated operator grants no
    session. The drone is told so, throttles its camera or falls back, and its setpoints never pause."""
    out = tmp_path / "run"
    result = subprocess.run(
        [DYNQOS, "demo", "--scenario", "bg-dynqos-refused", "--duration", "24", "--out", str(out)],
        capture_output=True, text=True, timeout=360, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "bg-dynqos-refused" / "summary.json").read_text())
    assert summary["ok"] is True, summary["failure"]
    network = summary["qos_network"]
    assert network["decision_to_available_s"] is None  # never granted
    assert network["sessions"]["refused"] >= 1
    assert network["sessions"]["open_at_end"] == 0
    assert summary["first_qos_switch_after_bg_s"] is not None  # it did ask, by moving to the priority flow
    adapting = sum(summary["states_time_s"][q] for q in ("q4", "q5", "q6", "qA"))
    assert adapting > 1.0, summary["states_time_s"]
    assert summary["setpoint_gap_max_ms"] < T_WD_MS
    causes = [t["cause"] for t in summary["transitions"]]
    assert any("the network refused" in c for c in causes), causes
