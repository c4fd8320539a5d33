"""The whole loop against PX4's own flight stack (PX4 SITL with SIH physics, docs/px4.md): the paper's
dynamic-QoS scenario flown by PX4 with every edge service, and the onboard daemon killed mid-flight so
that PX4's own offboard-loss failsafe takes over with the parameters dynqos boots it with. What PX4 did
is read from PX4's side (its heartbeat and its own ULog), not from dynqos's. Skipped where no PX4 build is
at hand."""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common import mavsign
from dynqos.common.config import ZenohConfig
from dynqos.experiment.runner import run_scenario
from dynqos.onboard.fclink import PX4_MAIN_AUTO, PX4_MAIN_OFFBOARD
from dynqos.plan.faults import Fault
from dynqos.plan.scenario import builtin_scenario
from dynqos.reports.px4_log import px4_report
from dynqos.sim.vehicle.px4_sitl import Px4Ports, free_instances
from tests.conftest import flow_ports
from tests.flights import fly_for_behaviour
from tests.procs import DynqosProcess
from tests.test_faults import _check

pytestmark = [pytest.mark.slow, pytest.mark.integration]
PX4_SUB_LAND = 6
DYNQOS = [sys.executable, "-m", "dynqos.cli"]


@pytest.mark.timeout(300)
def test_px4_flies_dynamic_qos_in_offboard_throughout_on_the_priority_flow_under_load(
    px4_dir: Path, tmp_path: Path
) -> None:
    scenario = replace(
        builtin_scenario("bg-dynqos"),
        duration_s=24.0,
        bg_start_s=12.0,
        vehicle="px4",
        config={"px4": {"dir": str(px4_dir)}},
    )
    result = run_scenario(scenario, tmp_path, progress=False)
    assert result["ok"], result["failure"]
    assert result["vehicle"] == "px4"
    px4 = result["px4"]
    modes = [m["mode"] for m in px4["modes"]]
    assert "AUTO_TAKEOFF" in modes, modes  # PX4's own take-off, as the daemon asked
    assert modes.index("AUTO_TAKEOFF") < modes.index("OFFBOARD"), modes
    assert modes[modes.index("OFFBOARD") + 1] == "AUTO_LAND", modes  # and its landing at the end
    assert px4["offboard_whole_flight"], px4["modes"]
    assert px4["failsafes"] == []
    # whatever PX4 said reached the summary through the drone's status, each in PX4's own sentence (its
    # event catalogue); a clean flight may have none: PX4 speaks up on trouble (tests/test_fc_said.py)
    said = result["fc_said"]
    assert all(s["text"] and 0 <= s["severity"] <= 7 for s in said), said
    assert not any(s["text"].startswith("PX4 event 0x") for s in said), said
    print(f"PX4 said: {[(s['t_s'], s['text']) for s in said]}")
    assert not result["fallback_entered"]
    switch_s = result["first_qos_switch_after_bg_s"]
    assert switch_s is not None, result["transitions"]
    assert switch_s < 3.0
    baseline, loaded = result["rtt_ms"]["baseline"]["mean"], result["rtt_ms"]["loaded"]["mean"]
    print(f"PX4: RTT {baseline:.1f} ms before the load, {loaded:.1f} ms under it; switch after {switch_s} s")
    assert loaded <= 1.5 * baseline
    assert sorted((tmp_path / scenario.run_id / "px4").glob("i*/log/**/*.ulg")), "the ULog was not kept"


@pytest.mark.timeout(240)
def test_signed_px4_refuses_unsigned_commands_and_its_failsafe_lands_when_the_daemon_dies(
    px4_dir: Path, tmp_path: Path
) -> None:
    """PX4 boots with a key and the daemon flies signed with it (`dynqos onboard check`'s signing item
    passes first). An unsigned and a wrongly signed command to land and to disarm, sent to PX4's
    ground-station link, change nothing in PX4's state and get no answer. Then SIGKILL ends the daemon's
    setpoints: after COM_OF_LOSS_T PX4 takes COM_OBL_RC_ACT = Land (dynqos's boot parameters), lands and
    disarms by itself. PX4's side is read from its own heartbeat and ULog."""
    instance = free_instances(1)[0]
    ports = Px4Ports(instance)
    zenoh = ZenohConfig(**flow_ports())
    key, other_key = mavsign.write_key(tmp_path / "fc.key"), mavsign.write_key(tmp_path / "other.key")
    config = tmp_path / "dynqos.toml"
    config.write_text(
        f'[px4]\ndir = "{px4_dir}"\nsigning_key = "{key}"\n'
        f"[zenoh]\ndefault_port = {zenoh.default_port}\npriority_port = {zenoh.priority_port}\n"
        f'[onboard]\nmavlink_url = "udpin:127.0.0.1:{ports.offboard_remote}"\nmavlink_signing_key = "{key}"\n'
        f'fc_system_id = {ports.system_id}\ncamera = "none"\nhealth_interval_s = 1\n'
    )
    workdir = tmp_path / "px4"
    procs: dict[str, DynqosProcess] = {}
    ground = intruder = None
    try:
        procs["px4"] = DynqosProcess(
            ["sim", "px4", "--instance", str(instance), "--workdir", str(workdir)], config, 60
        )
        assert procs["px4"].info["signing"] == "on"
        procs["router"] = DynqosProcess(["edge", "router"], config)
        check = subprocess.run(
            [*DYNQOS, "onboard", "check", "--config", str(config)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        signing = [line for line in check.stdout.splitlines() if "MAVLink signing" in line]
        assert signing, check.stdout
        assert signing[0].startswith("PASS"), check.stdout
        assert "signed messages checked, 0 refused" in signing[0]
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config)
        airborne = any("offloading" in line for line in procs["onboard"].lines(timeout_s=60))
        assert airborne, "the daemon never flew offboard on PX4"
        ground = GroundStation(ports)
        assert ground.heard(lambda: ground.mode() == (PX4_MAIN_OFFBOARD, 0) and ground.armed(), 10)
        intruder = _signed_with(mavsign.load_key(other_key), ports)
        for mav in (
            ground.mav,
            intruder.mav,
        ):  # unsigned (the ground station's link), then signed with another key
            mav.command_long_send(
                ports.system_id, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, PX4_MAIN_AUTO, PX4_SUB_LAND, 0, 0, 0, 0
            )
            mav.command_long_send(
                ports.system_id, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, FORCE, 0, 0, 0, 0, 0
            )
        assert not ground.heard(lambda: ground.mode() != (PX4_MAIN_OFFBOARD, 0) or not ground.armed(), 3)
        assert ground.acks == [], "PX4 answered a command it should have dropped"
        health = list(
            itertools.islice(
                (line for line in procs["onboard"].lines(timeout_s=5) if "fc_signed_ok=" in line), 3
            )
        )  # the third from now on is after the intruders (one a second)
        assert len(health) == 3, "no health line with the signing counters"
        assert " fc_refused=0" in health[-1]
        procs["onboard"].proc.send_signal(signal.SIGKILL)  # our own child, by its pid
        procs["onboard"].stop()
        assert ground.heard(lambda: ground.mode() == (PX4_MAIN_AUTO, PX4_SUB_LAND), 15), "PX4 did not land"
        assert ground.heard(lambda: not ground.armed(), 60), "PX4 did not disarm after landing"
    finally:
        for name in reversed(list(procs)):
            procs[name].stop()
        for conn in (ground, intruder):
            if conn is not None:
                conn.close()
    report = px4_report(workdir, flight_s=0.0)
    modes = [m["mode"] for m in report["modes"]]
    # Nothing the intruders sent moved PX4 out of OFFBOARD before the failsafe
    assert modes[modes.index("OFFBOARD") + 1] == "AUTO_LAND", modes
    assert modes[: modes.index("AUTO_LAND")].count("OFFBOARD") == 1, modes
    assert [f["mode"] for f in report["failsafes"]] == ["AUTO_LAND"], report["failsafes"]


FORCE = 21196  # MAV_CMD_COMPONENT_ARM_DISARM's param2: disarm even in flight


class GroundStation:
    """PX4's ground-station link as a ground station without the key uses it: PX4 answers whoever talks to
    its port, and a reader without a key reads signed messages without checking them."""

    def __init__(self, ports: Px4Ports) -> None:
        self.conn = mavlink2(ports, 255)
        self.mav = self.conn.mav
        self.system_id = ports.system_id
        self.acks: list[int] = []
        self.last: object | None = None

    def heard(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Reads PX4 (saying hello once a second) until `predicate` holds on its last heartbeat."""
        deadline = time.monotonic() + timeout_s
        next_hello = 0.0
        while time.monotonic() < deadline:
            if time.monotonic() >= next_hello:
                next_hello = time.monotonic() + 1.0
                self.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            msg = self.conn.recv_match(type=["HEARTBEAT", "COMMAND_ACK"], blocking=True, timeout=0.2)
            if msg is None or msg.get_srcSystem() != self.system_id:
                continue
            if msg.get_type() == "COMMAND_ACK":
                self.acks.append(msg.command)
            elif msg.get_srcComponent() == 1:
                self.last = msg
                if predicate():
                    return True
        return False

    def mode(self) -> tuple[int, int]:
        custom = getattr(self.last, "custom_mode", 0)
        return (custom >> 16) & 0xFF, (custom >> 24) & 0xFF

    def armed(self) -> bool:
        return bool(getattr(self.last, "base_mode", 0) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def close(self) -> None:
        self.conn.close()


def mavlink2(ports: Px4Ports, system_id: int) -> Any:
    """A link to PX4's ground-station port that speaks MAVLink 2 from its first byte, as PX4 does (without
    setting MAVLINK20 for the whole test process)."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{ports.gcs_local}", source_system=system_id)
    conn.mav = mavlink.MAVLink(conn, srcSystem=system_id, srcComponent=mavlink.MAV_COMP_ID_MISSIONPLANNER)
    conn.mav.robust_parsing = True
    return conn


def _signed_with(key: bytes, ports: Px4Ports) -> Any:
    """A second sender to PX4's ground-station port, signing with `key` (not PX4's)."""
    conn = mavlink2(ports, 254)
    conn.setup_signing(key, sign_outgoing=True, initial_timestamp=mavsign.timestamp_now(), link_id=7)
    return conn


@pytest.mark.timeout(600)  # a flight that failed on cores not its own is flown again
def test_a_fleet_of_px4_instances_flies_the_arbiters_contrast(px4_dir: Path, tmp_path: Path) -> None:
    """fleet-arbiter, shortened, with each drone flown by its own PX4 instance, standing where the scenario
    places it in one frame: every PX4 flew the whole flight in OFFBOARD with no failsafe, and the
    arbiter's contrast holds as on dynqos's vehicles (docs/fleet.md): the high-risk drone holds
    priority and stays below the denied drone's RTT at its full camera rate. Two of its four drones (a
    high-risk and a low-risk one, one grant): four PX4 instances and the fleet kept this 2-core machine
    89% busy, and three 75% (docs/px4.md)."""
    arbiter = builtin_scenario("fleet-arbiter")
    scenario = replace(
        arbiter,
        drones=(arbiter.drones[0], arbiter.drones[2]),
        arbiter_max_grants=1,
        duration_s=30.0,
        bg_start_s=12.0,
        vehicle="px4",
        config={**arbiter.config, "px4": {"dir": str(px4_dir)}},
    )
    fly_for_behaviour(lambda out: run_scenario(scenario, out, progress=False), tmp_path, _check_px4_fleet)


def _check_px4_fleet(summary: dict[str, Any], _: Path) -> None:
    print(f"PX4 fleet: machine {summary['machine']}, failure {summary['failure']!r}")
    assert summary["vehicle"] == "px4"
    for uav, drone in summary["drones"].items():
        assert drone["px4"]["offboard_whole_flight"], (uav, drone["px4"]["modes"])
        assert drone["px4"]["failsafes"] == [], uav
    high, low = summary["drones"]["uav1"], summary["drones"]["uav3"]
    assert (high["risk_zone"], low["risk_zone"]) == ("high", "low")
    assert high["rtt_ms"]["loaded"]["mean"] < low["rtt_ms"]["loaded"]["mean"]
    assert high["camera_fps"]["loaded"] >= 0.9 * high["camera_fps"]["configured"]
    assert high["granted_time_s"] > 0.5 * summary["duration_s"]
    assert low["granted_time_s"] < 0.2 * summary["duration_s"]
    assert summary["qod_sessions"]["open_at_end"] == 0


@pytest.mark.timeout(420)  # a flight that failed on cores not its own is flown again
def test_on_px4_the_onboard_fallback_takes_each_fault_and_px4s_own_failsafe_never_fires(
    px4_dir: Path, tmp_path: Path
) -> None:
    """The MPC killed, the coverage and the downlink lost, on PX4: the onboard fallback takes over within
    T_wd as on dynqos's vehicle and keeps streaming, so PX4 stays in OFFBOARD throughout (its ULog) and
    its offboard-loss failsafe never fires; the drone returns to the edge after each."""
    faults = (
        Fault(at_s=5.0, kind="mpc_kill", duration_s=2.0),
        Fault(at_s=13.0, kind="coverage_loss", duration_s=2.0),
        Fault(at_s=21.0, kind="downlink_loss", duration_s=2.0),
    )
    scenario = replace(
        builtin_scenario("faults"),
        duration_s=30.0,
        faults=faults,
        vehicle="px4",
        config={"px4": {"dir": str(px4_dir)}},
    )
    fly_for_behaviour(lambda out: run_scenario(scenario, out, progress=False), tmp_path, _check_px4_faults)


def _check_px4_faults(result: dict[str, Any], _: Path) -> None:
    _check(result, {"mpc_kill", "coverage_loss", "downlink_loss"})
    assert result["px4"]["offboard_whole_flight"], result["px4"]["modes"]
    assert result["px4"]["failsafes"] == []
