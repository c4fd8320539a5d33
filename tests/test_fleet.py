"""A fleet in one cell (docs/fleet.md): the configs every process reads, and a short fleet flight over
real processes with the arbiter: the summary contract, and the high-risk drones keeping their loop."""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.config import ZenohConfig, load_config
from dynqos.common.errors import ConfigError
from dynqos.common.messages import State
from dynqos.experiment.runner import run_scenario
from dynqos.plan.cells import with_cell
from dynqos.plan.faults import Fault
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import (
    FLEET_FAULTS,
    builtin_scenario,
    fleet_configs,
    load_scenario,
    write_config,
)
from dynqos.reports.fleet import _queue_delays, summarise_fleet
from tests.flights import fly_for_behaviour, run_file
from tests.statuses import status_saying

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


def test_a_fleet_takes_the_edges_faults_and_refuses_one_drones_with_the_reason(tmp_path: Path) -> None:
    scenario = builtin_scenario("fleet-replicas")
    assert scenario.fleet
    assert (scenario.mpc_replicas, scenario.planner_replicas, scenario.qos_agents) == (2, 2, 2)
    assert {f.kind for f in scenario.faults} <= set(FLEET_FAULTS)
    path = tmp_path / "fleet-coverage.toml"
    text = (Path(str(resources.files("dynqos") / "scenarios" / "fleet-arbiter.toml"))).read_text()
    fault = '[[scenario.faults]]\nat_s = 5\nkind = "coverage_loss"\n\n'
    path.write_text(text.replace("[[scenario.drones]]", fault + "[[scenario.drones]]", 1))
    with pytest.raises(ConfigError, match=r"faults\[0\]\.kind.*coverage_loss acts on one drone's link"):
        load_scenario(path)


def _without_uav4(shipped: str) -> str:
    """A shipped fleet scenario's text without its fourth drone (both high-risk drones and a low-risk one
    stay): with all four, two slow cores are what the flight measures (the comment above OTHER_MODES)."""
    uav4 = '[[scenario.drones]]\nid = "uav4"\n'
    return shipped[: shipped.index(uav4)] + shipped[shipped.index("\n\n", shipped.index(uav4)) + 2 :]


def _fly_arbitrated(out: Path) -> dict[str, Any]:
    """fleet-arbiter, three of its drones, 30 s with the load from 15 s (as `dynqos demo --duration 30`)."""
    text = _without_uav4((resources.files("dynqos") / "scenarios" / "fleet-arbiter.toml").read_text())
    for old, new in (("duration_s = 45", "duration_s = 30"), ("bg_start_s = 20", "bg_start_s = 15")):
        assert old in text, old
        text = text.replace(old, new)
    scenario = out.parent / f"{out.name}.toml"
    scenario.write_text(text)
    assert [d.id for d in load_scenario(scenario).drones] == ["uav1", "uav2", "uav3"]
    return _flown(run_file(scenario, out), out, "fleet-arbiter")


def _flown(result: subprocess.CompletedProcess[str], out: Path, name: str) -> dict[str, Any]:
    """The summary of scenario `name` that a `dynqos` command flew into `out`; it exited 0 if ok, else 1."""
    summary: dict[str, Any] = json.loads((out / name / "summary.json").read_text())
    assert result.returncode == (0 if summary["ok"] else 1), result.stderr[-3000:]
    return summary


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)  # a flight that failed while starved is flown again
def test_a_short_arbitrated_fleet_flight_keeps_the_high_risk_drones_loop(tmp_path: Path) -> None:
    """fleet-arbiter, shortened: three of its drones, both high-risk ones and a low-risk one, one busy cell
    and room for two grants. The high-risk drones hold priority and keep their RTT within the scenario's
    1.2x and their full camera rate under load; the other is denied and adapts; no drone's setpoints pause
    over 100 ms; no QoD session is left. As every behaviour flight (tests/flights.py): a starved flight
    whose behaviour holds passed the harder way; one that broke it while starved, or while the host took
    the cores, is flown once more and asserted whatever its machine. Three drones, not four: in the
    project's CI of 2026-12-01 (commit 017226f) the four-drone flight broke the high-risk drones' RTT
    bound and the 100 ms setpoint bound in both tries, each time on its second flight after a disturbed
    first one, while the same code's four held them here at 63% busy, and in a 1-core CPU quota. Four
    drones cost a host 1.5 cores or more; whether they starve it is the `fleet_flight` benchmark's
    (docs/benchmarks.md), which flies all four. A failure prints every drone's figures
    (_what_each_drone_did): that CI's report showed only the first keys of the summary."""
    fly_for_behaviour(_fly_arbitrated, tmp_path, _check_arbitrated)


def _what_each_drone_did(summary: dict[str, Any]) -> str:
    """A failed fleet check's figures, whole (pytest shortens the repr of a long dict to its first keys):
    the machine, then per drone its risk, RTT (baseline mean, loaded mean and p99), largest setpoint gap,
    fallback and time granted."""

    def ms(value: float | None) -> str:
        return "none" if value is None else f"{value:.1f} ms"

    lines = [f"machine {summary['machine']}"]
    for uav, d in summary["drones"].items():
        baseline, loaded = d["rtt_ms"]["baseline"] or {}, d["rtt_ms"]["loaded"] or {}
        lines.append(
            f"{uav} ({d['risk_zone']} risk): rtt baseline {ms(baseline.get('mean'))}, loaded "
            f"{ms(loaded.get('mean'))} (p99 {ms(loaded.get('p99'))}), x{d['rtt_loaded_over_baseline']}; "
            f"largest setpoint gap {ms(d['setpoint_gap_max_ms'])}; fallback {d['fallback_entered']}; "
            f"granted {d['granted_time_s']} s"
        )
    return "\n".join(lines)


def _check_arbitrated(summary: dict[str, Any], out: Path) -> None:
    machine = summary["machine"]
    assert machine["seconds_sampled"] >= 25, machine
    assert 0 < machine["busy_share"] <= machine["busy_share_max_1s"] <= 1, machine
    busy, peak = machine["busy_share"], machine["busy_share_max_1s"]
    print(f"the fleet kept the machine {busy:.0%} busy (busiest second {peak:.0%})")
    assert all(summary["checks"].values()), f"{summary['checks']}\n{_what_each_drone_did(summary)}"
    assert set(summary["checks"]) == {
        "high_risk_rtt_within_1_2x", "high_risk_delivered_95pct", "setpoint_gaps_within_100ms",
        "every_drone_heard",
    }  # fmt: skip
    assert set(summary["drones"]) == {"uav1", "uav2", "uav3"}
    for uav, drone in summary["drones"].items():
        assert set(drone) >= DRONE_KEYS, (uav, DRONE_KEYS - set(drone))
    assert set(summary["arbiter"]) >= {"grants", "denials", "revocations"}
    assert summary["arbiter"]["grants"] >= 2
    assert summary["qod_sessions"]["open_at_end"] == 0
    assert summary["cpu_s"]["mpc"] > 0
    high = {u: d for u, d in summary["drones"].items() if d["risk_zone"] == "high"}
    low = {u: d for u, d in summary["drones"].items() if d["risk_zone"] == "low"}
    assert len(high) == 2
    denied_rtt = min(d["rtt_ms"]["loaded"]["mean"] for d in low.values())
    for uav, drone in high.items():
        # the arbiter kept their loop (its 1.2x is in `checks` above): below the denied drones' RTT and at
        # the full camera rate
        loaded = drone["rtt_ms"]["loaded"]["mean"]
        assert loaded < denied_rtt, (uav, loaded, denied_rtt, drone["cell_queue_ms"])
        assert drone["camera_fps"]["loaded"] >= 0.9 * drone["camera_fps"]["configured"], uav
        assert drone["uav_delivered_mbps"] >= 0.95 * drone["uav_admitted_mbps"], uav
        assert drone["granted_time_s"] > 0.5 * summary["duration_s"], uav
    for uav, drone in low.items():
        assert drone["granted_time_s"] < 0.2 * summary["duration_s"], (
            uav
        )  # the budget was the high-risk drones'
    # A low-risk drone that asked for priority (a priority-flow state other than qA, docs/supervisor.md)
    # was denied; one whose watchdog fired first went to its fallback without asking (qA asks only
    # when it came from a state that wanted priority), and nobody was there to deny.
    asked = [
        u for u, d in low.items() if any(d["states_time_s"].get(q, 0) > 0 for q in ("q2", "q3", "q5", "q6"))
    ]
    print(f"low-risk drones that asked for priority: {asked or 'none (their watchdog fired first)'}")
    if asked:
        assert summary["arbiter"]["denials"] >= 1, (asked, summary["arbiter"])
    assert (out / "fleet-arbiter" / "timeline.png").exists()
    report = (out / "report.md").read_text()
    assert "## Fleets" in report
    assert "| uav1 | high |" in report


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)  # a flight that failed while starved is flown again
def test_a_fleet_on_a_replicated_edge_never_falls_back_when_its_replicas_are_killed_or_hung(
    tmp_path: Path,
) -> None:
    """fleet-replicas, its faults and timeline whole, on three of its drones (as in the fleet's other
    modes below: with all four its first flight here was starved for 40 of its 45 s and flown again):
    two MPC and two planner replicas, two QoS agents; the MPC replica serving uav1 is killed, a third
    joins, the serving one is hung, the serving planner is killed, the active QoS agent is killed. No
    drone falls back, none of its setpoints pauses over 100 ms, the standby agent serves uav1's grant,
    the same session, within 2 s."""
    three = tmp_path / "fleet-replicas.toml"
    three.write_text(
        _without_uav4((resources.files("dynqos") / "scenarios" / "fleet-replicas.toml").read_text())
    )
    assert [d.id for d in load_scenario(three).drones] == ["uav1", "uav2", "uav3"]

    fly_for_behaviour(lambda out: _flown(run_file(three, out), out, "fleet-replicas"), tmp_path, _check_whole)


def _check_whole(summary: dict[str, Any], out: Path) -> None:
    kinds = [f["kind"] for f in summary["faults"]]
    assert kinds == ["mpc_replica_kill", "replica_join", "mpc_replica_hang", "planner_replica_kill",
                     "qos_agent_kill"]  # fmt: skip
    for fault in summary["faults"]:
        print(f"{fault['kind']} on {fault['target']}: fell back {fault['fell_back'] or 'none'}, "
              f"longest setpoint gap {fault['max_setpoint_gap_ms']} ms; {fault['notes']}")  # fmt: skip
        assert fault["target"], fault  # it acted on a live process
        assert fault["fell_back"] == [], fault
        assert fault["max_setpoint_gap_ms"] is not None
        assert fault["max_setpoint_gap_ms"] < 100, fault
    assert summary["checks"]["no_fallback_in_faults"] is True
    for uav, drone in summary["drones"].items():
        assert drone["fallback_entered"] is False, uav
        assert len(drone["faults"]) == len(kinds), uav
    kill = summary["faults"][kinds.index("mpc_replica_kill")]
    assert "served the drone" in kill["notes"][0], kill  # the replica flying uav1, by its own State
    agent = summary["faults"][kinds.index("qos_agent_kill")]["grant"]
    assert agent["before"] == agent["after"] == "available", agent
    assert agent["same_session"] is True, agent
    assert agent["served_after_s"] < 2.0, agent
    assert summary["qod_sessions"]["conflicts"] == 0
    assert summary["qod_sessions"]["open_at_end"] == 0
    assert "- fault mpc_replica_kill at 8 s for 2 s on mpc" in (out / "report.md").read_text()


# The fleet's other two modes (fleet-allprio's policy, fleet-noqos's flow): the same replicated edge and
# faults, closer together. Commands reach a drone on the flow it flies, so a takeover meets each one.
# Three of the fleet's drones (both high-risk ones and a low-risk one): with all four and the edge's ten
# processes every camera runs at its full rate here, and two slow cores were 95-97% busy for the whole
# flight, so a drone fell back because its commands waited for a core, not for a replica (the CI of
# 2026-11-30: a solve took 0.16 ms, not 0.11). The arbiter's mode above flies the same three.
OTHER_MODES = {
    "allprio": ("dynamic", ("mpc_replica_kill", "replica_join", "mpc_replica_hang", "planner_replica_kill",
                            "qos_agent_kill")),
    "noqos": ("default", ("mpc_replica_kill", "replica_join", "mpc_replica_hang", "planner_replica_kill")),
}  # fmt: skip


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)  # a flight that failed while starved is flown again
@pytest.mark.parametrize("mode", sorted(OTHER_MODES))
def test_a_replicated_edge_keeps_every_drone_out_of_its_fallback_in_the_fleets_other_modes(
    mode: str, tmp_path: Path
) -> None:
    """fleet-replicas (three of its drones) with every drone granted what it asks (allprio) or none
    asking (noqos), the faults 5 s apart: no drone falls back, no setpoint pauses over 100 ms, and in
    allprio the standby QoS agent serves uav1's grant, the same session, within 2 s."""
    qos, kinds = OTHER_MODES[mode]
    base = builtin_scenario("fleet-replicas")
    faults = tuple(Fault(at_s=6.0 + 5.0 * i, kind=kind, duration_s=3.0 if kind == "qos_agent_kill" else 2.0)
                   for i, kind in enumerate(kinds))  # fmt: skip
    scenario = replace(base, name=f"fleet-replicas-{mode}", qos=qos, qos_policy="grant-all", faults=faults,
                       duration_s=faults[-1].at_s + 8.0, drones=base.drones[:3])  # fmt: skip
    assert [d.risk_zone for d in scenario.drones] == ["high", "high", "low"]

    def check(summary: dict[str, Any], _: Path) -> None:
        assert [f["kind"] for f in summary["faults"]] == list(kinds)
        for fault in summary["faults"]:
            print(f"{mode}: {fault['kind']} on {fault['target']}: fell back {fault['fell_back'] or 'none'}, "
                  f"longest setpoint gap {fault['max_setpoint_gap_ms']} ms; {fault['notes']}")  # fmt: skip
            assert fault["target"], fault
            assert fault["fell_back"] == [], fault
            assert fault["max_setpoint_gap_ms"] is not None
            assert fault["max_setpoint_gap_ms"] < 100, fault
        assert "served the drone" in summary["faults"][0]["notes"][0]
        for uav, drone in summary["drones"].items():
            assert drone["fallback_entered"] is False, uav
            if qos == "default":  # the mode does what it says: nobody is granted priority
                assert drone["granted_time_s"] == 0, uav
        if qos == "dynamic":  # and here the high-risk drone holds it (granted, as every drone is asked)
            assert summary["drones"]["uav1"]["granted_time_s"] > 0.5 * scenario.duration_s
        if "qos_agent_kill" in kinds:
            grant = summary["faults"][kinds.index("qos_agent_kill")]["grant"]
            assert grant["before"] == grant["after"] == "available", grant
            assert grant["same_session"] is True, grant
            assert grant["served_after_s"] < 2.0, grant
        assert summary["qod_sessions"]["conflicts"] == 0
        assert summary["qod_sessions"]["open_at_end"] == 0

    fly_for_behaviour(lambda out: run_scenario(scenario, out, progress=False), tmp_path, check)


def test_a_drone_never_heard_in_the_flight_fails_the_fleets_check() -> None:
    """A drone stuck where its link carries nothing (a coverage hole it holds in) has no figures; the
    fleet's summary says so instead of an entry that looks quiet (docs/radio.md, "In a fleet")."""
    scenario = builtin_scenario("fleet-arbiter")

    def heard(uav: str) -> Recording:
        state = State(uav=uav, seq=1, stamp_ns=1, pos_m=(0.0, 0.0, -1.5), vel_mps=(0.0, 0.0, 0.0),
                      quat=(1.0, 0.0, 0.0, 0.0))  # fmt: skip
        return Recording(states=[(10.0, state)])

    all_heard = {d.id: heard(d.id) for d in scenario.drones}
    said = status_saying(3, "Failsafe enabled: no offboard", 4, uav="uav2")
    all_heard["uav2"] = replace(all_heard["uav2"], status=[said])
    summary = summarise_fleet(scenario, Recording(), all_heard, [], {}, ok=True, failure="")
    assert summary["checks"]["every_drone_heard"] is True
    # what each drone's flight controller said, in its own entry
    assert summary["drones"]["uav2"]["fc_said"] == [
        {"t_s": 0.0, "severity": 4, "text": "Failsafe enabled: no offboard"}
    ]
    assert summary["drones"]["uav1"]["fc_said"] == []
    one_silent = all_heard | {"uav1": Recording()}
    summary = summarise_fleet(scenario, Recording(), one_silent, [], {}, ok=True, failure="")
    assert summary["checks"]["every_drone_heard"] is False
    assert summary["drones"]["uav1"]["states_recorded"] == 0
