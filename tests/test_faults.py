"""Faults in a loopback flight: what each does to the drone, measured from its log and
status stream. The pure parts are tested here quickly; the flights are marked slow (CI runs them)."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority
from dynqos.common.errors import ConfigError
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import QosGrant, Reference, State, SupervisorStatus
from dynqos.common.modes import Grant
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.processes import Processes
from dynqos.experiment.runner import run_scenario
from dynqos.plan.faults import Fault, FaultWindow
from dynqos.plan.scenario import Scenario, builtin_scenario
from dynqos.reports.outcomes import log_times, outcome, time_in_states
from tests.flights import fly_for_behaviour, starved
from tests.statuses import status

T_WD_MS = 150.0
TICK_MS = 20.0


def _status(
    stamp_ns: int,
    gap_ms: float | None,
    source: str = "edge",
    changed_ns: int = 0,
    age_ms: float | None = None,
) -> SupervisorStatus:
    return status(
        stamp_ns=stamp_ns,
        control_source=source,
        setpoint_gap_ms=gap_ms,
        control_changed_ns=changed_ns,
        command_age_ms=age_ms,
        fallbacks=int(source != "edge"),
    )


def test_faults_are_validated() -> None:
    with pytest.raises(ConfigError, match="duration_s"):
        Fault(at_s=1, kind="mpc_kill", duration_s=0)
    with pytest.raises(ConfigError, match="faults"):
        Scenario(
            name="x", duration_s=10, bg_start_s=-1, faults=(Fault(at_s=9, kind="mpc_kill", duration_s=2),)
        )
    assert builtin_scenario("faults").faults  # the shipped fault scenario loads
    soak = builtin_scenario("soak")
    assert soak.duration_s == 600
    assert [f.at_s for f in soak.faults] == [30 + 60 * k for k in range(10)]


def test_replica_faults_need_a_standby() -> None:
    with pytest.raises(ConfigError, match="mpc_replicas >= 2"):
        Scenario(name="x", duration_s=10, bg_start_s=-1, faults=(Fault(at_s=1, kind="mpc_replica_hang"),))
    with pytest.raises(ConfigError, match="mpc_replicas"):
        Scenario(name="x", duration_s=10, bg_start_s=-1, mpc_replicas=9)
    with pytest.raises(ConfigError, match="planner_replicas >= 2"):
        Scenario(name="x", duration_s=10, bg_start_s=-1, faults=(Fault(at_s=1, kind="planner_replica_kill"),))
    with pytest.raises(ConfigError, match="qos_agents >= 2"):
        Scenario(name="x", duration_s=10, bg_start_s=-1, faults=(Fault(at_s=1, kind="qos_agent_kill"),))
    with pytest.raises(ConfigError, match="qos_agents"):
        Scenario(name="x", duration_s=10, bg_start_s=-1, qos_agents=0)
    replicas = builtin_scenario("replicas")
    assert (replicas.mpc_replicas, replicas.planner_replicas, replicas.qos_agents) == (2, 2, 2)


SLEEPER = [sys.executable, "-c", "import time; print('{}', flush=True); time.sleep(120)"]


def test_replica_faults_act_on_the_replica_the_drone_says_flies_it(tmp_path: Path) -> None:
    """Real child processes (stand-ins that only wait) under the runner's Processes; the drone's State
    on the bus names the replica it follows, and that one is killed and restarted, then stopped and
    resumed."""
    procs = Processes(tmp_path / "run.toml", tmp_path)
    bus = MemoryBus()
    try:
        for name in ("mpc", "mpc-1"):
            procs.start(name, [], program=SLEEPER)
        injector = FaultInjector(procs, lambda event: None, bus, watch_uav="uav1")
        state = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
        state.put(State(uav="uav1", seq=1, stamp_ns=1, pos_m=(0.0, 0.0, 0.0), vel_mps=(0.0, 0.0, 0.0),
                        quat=(1.0, 0.0, 0.0, 0.0), command_term=3, command_replica="mpc-1"))  # fmt: skip
        first_pid = procs.procs["mpc-1"].pid
        window = injector.begin(Fault(at_s=1, kind="mpc_replica_kill", duration_s=1))
        assert (window.target, window.notes) == ("mpc-1", ["mpc-1 served the drone (term 3)"])
        assert procs.procs["mpc-1"].poll() is not None  # killed
        assert procs.procs["mpc"].poll() is None  # the standby untouched
        injector.end(window)
        assert procs.procs["mpc-1"].poll() is None
        assert procs.procs["mpc-1"].pid != first_pid  # restarted
        # No state since: the injector says so and acts on the first live replica.
        hang = injector.begin(Fault(at_s=3, kind="mpc_replica_hang", duration_s=1))
        assert hang.target == "mpc"
        assert "no live mpc replica was seen serving" in hang.notes[0]
        assert _reaches(procs.procs["mpc"].pid, stopped=True)
        injector.end(hang)
        assert _reaches(procs.procs["mpc"].pid, stopped=False)
        # The planner replica that sent the drone's latest reference is the one a planner fault acts on.
        for name in ("planner", "planner-1"):
            procs.start(name, [], program=SLEEPER)
        refs = bus.publisher(keys.downlink("uav1", Downlink.REFERENCE), Priority.INTERACTIVE_HIGH)
        refs.put(Reference(uav="uav1", seq=1, stamp_ns=1, dt_s=0.05, pos_m=((0.0, 0.0, -1.5),),
                           vel_mps=((0.0, 0.0, 0.0),), yaw_rad=(0.0,), mission_t_s=12.0, term=2,
                           replica="planner-1"))  # fmt: skip
        planner = injector.begin(Fault(at_s=5, kind="planner_replica_kill", duration_s=1))
        assert (planner.target, planner.notes) == ("planner-1", ["planner-1 served the drone (term 2)"])
        assert procs.procs["planner-1"].poll() is not None
        assert procs.procs["planner"].poll() is None
        # The QoS agent holding the active token is the one killed; the grant told after it is measured.
        for name in ("qos", "qos-1"):
            procs.start(name, [], program=SLEEPER)
        grants = bus.publisher(keys.downlink("uav1", Downlink.QOS_GRANT), Priority.INTERACTIVE_HIGH)
        grants.put(QosGrant(uav="uav1", seq=7, grant=Grant.AVAILABLE, backend="camara", session_id="s1"))
        token = bus.declare_token(keys.qos_active("all", "qos-1"))
        agent = injector.begin(Fault(at_s=7, kind="qos_agent_kill", duration_s=1))
        token.close()  # it died with its process
        assert (agent.target, agent.notes) == ("qos-1", ["qos-1 was the active agent"])
        assert procs.procs["qos-1"].poll() is not None
        assert procs.procs["qos"].poll() is None
        grants.put(QosGrant(uav="uav1", seq=1, grant=Grant.AVAILABLE, backend="camara", session_id="s1"))
        injector.end(agent)
        assert agent.grant is not None
        assert agent.grant["before"] == agent.grant["after"] == "available"
        assert agent.grant["same_session"]
        assert 0 <= agent.grant["served_after_s"] < 1.0
        assert procs.procs["qos-1"].poll() is None  # restarted
    finally:
        procs.stop_all()
        bus.close()


def _reaches(pid: int, *, stopped: bool, timeout_s: float = 10.0) -> bool:
    """Whether the process is (or stops being) stopped within the timeout: a signal takes effect when the
    kernel next schedules it, which on a loaded machine is not at once."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        if (state == "T") == stopped:
            return True
        time.sleep(0.01)
    return False


def test_time_in_states_lasts_each_state_until_the_next_status() -> None:
    ms = 1_000_000
    statuses = [
        replace(_status(t * ms, None), state=state)
        for t, state in [(0, "q1"), (200, "q1"), (500, "q3"), (1500, "q6"), (1600, "q6")]
    ]
    assert time_in_states(statuses) == pytest.approx({"q1": 0.5, "q3": 1.0, "q6": 0.1})
    assert time_in_states(statuses, since_ns=500 * ms) == pytest.approx({"q3": 1.0, "q6": 0.1})
    assert time_in_states(statuses[:1]) == {}
    # within a window, only the part of each span inside it (a booking's priority-seconds used)
    clipped = time_in_states(statuses, within=(300 * ms, 1550 * ms))
    assert clipped == pytest.approx({"q1": 0.2, "q3": 1.0, "q6": 0.05})


def test_outcome_measures_fallback_gaps_and_recovery_from_the_status_stream() -> None:
    log = log_times(
        "2026-11-22 08:00:00,000 INFO dynqos.onboard.daemon: onboard: control from the edge (seq 1)\n"
        "2026-11-22 08:00:10,160 WARNING dynqos.onboard.daemon: onboard: fallback PID holding position "
        "(watchdog: last valid command 162 ms ago)\n"
        "not a log line\n"
        "2026-11-22 08:00:13,500 INFO dynqos.onboard.daemon: onboard: control from the edge (seq 99)\n"
        "2026-11-22 08:00:30,000 WARNING dynqos.onboard.daemon: onboard: fallback PID holding position "
        "(watchdog: last valid command 170 ms ago)\n"
    )
    assert len(log) == 4
    s = 1_000_000_000
    start = log[0][0] + 10.0
    window = FaultWindow(Fault(at_s=10, kind="mpc_kill", duration_s=2), start, 10 * s)
    window.end_wall, window.end_ns = start + 2.0, 12 * s
    statuses = [
        _status(9 * s, 80.0),
        _status(10_160_000_000, 35.0, "fallback", 10_160_000_000, 162.0),  # published at the change
        _status(11 * s, 20.0, "fallback", 10_160_000_000, 162.0),
        _status(13_500_000_000, 20.0, "edge", 13_500_000_000, 3.0),
        _status(30 * s, 20.0, "fallback", 30 * s, 170.0),  # a later fault's
    ]
    got = outcome(window, log, statuses, next_start_ns=25 * s)
    assert got["fallback"] is True
    assert got["fallback_after_last_command_ms"] == 162.0
    assert got["fallback_after_fault_s"] == pytest.approx(0.16, abs=1e-3)
    assert got["max_setpoint_gap_ms"] == 35.0  # the 80 ms gap was before the fault
    assert got["back_at_edge_after_clear_s"] == pytest.approx(1.5, abs=1e-3)
    assert got["recovered"] is True
    # The 30 s fallback belongs to a later window: not reported here, and the next fault cuts it off.
    assert all("170 ms" not in line for line in got["log"])
    assert any("162 ms" in line for line in got["log"])
    # A fallback that never hands back is not a recovery; a window with no fallback is.
    stuck = outcome(window, log, statuses[:3], next_start_ns=None)
    assert (stuck["fallback"], stuck["recovered"], stuck["back_at_edge_after_clear_s"]) == (True, False, None)
    calm = outcome(window, log, [_status(11 * s, 20.0)], next_start_ns=None)
    assert (calm["fallback"], calm["recovered"], calm["fallback_after_last_command_ms"]) == (
        False,
        True,
        None,
    )
    assert not got["fallback_at_start"]
    assert not calm["fallback_at_start"]
    # A drone its fallback flew since before the fault began (an earlier fault's, not handed back): the
    # fault found it in its fallback, it caused none of it, and the hand-back is still measured.
    earlier = [
        _status(9_500_000_000, 20.0, "fallback", 9_400_000_000, 160.0),
        _status(11 * s, 20.0, "fallback", 9_400_000_000, 160.0),
        statuses[3],
    ]
    kept = outcome(window, log, earlier, next_start_ns=25 * s)
    assert (kept["fallback"], kept["fallback_at_start"], kept["recovered"]) == (True, True, True)
    assert (kept["fallback_after_last_command_ms"], kept["fallback_after_fault_s"]) == (None, None)
    assert kept["back_at_edge_after_clear_s"] == pytest.approx(1.5, abs=1e-3)
    assert not outcome(window, log, earlier[:1], next_start_ns=None)["recovered"]


class _NoProcs:
    """The injector's processes, for faults that touch only the cell."""

    launches = 0


class _Procs(_NoProcs):
    """The injector's processes, counted: a kill and a restart (which launches) by name."""

    def __init__(self) -> None:
        self.procs: dict[str, object] = {}
        self.down: set[str] = set()
        self.done: list[str] = []

    def kill(self, name: str) -> None:
        self.done.append(f"kill {name}")

    def restart(self, name: str) -> None:
        self.done.append(f"restart {name}")
        self.launches += 1


def test_a_fault_that_restarts_a_process_notes_when_on_its_window() -> None:
    """What dynqos/reports/machine.py keeps apart: the span from the fault's act to the ready line."""
    procs = _Procs()
    injector = FaultInjector(procs, lambda event: None, bus=None)  # type: ignore[arg-type]
    killed = injector.begin(Fault(at_s=5, kind="mpc_kill", duration_s=1))
    assert killed.restarts == []  # a kill starts nothing
    injector.end(killed)
    assert procs.done == ["kill mpc", "restart mpc"]
    assert len(killed.restarts) == 1
    began, ready = killed.restarts[0]
    assert killed.start_ns <= began <= ready <= (killed.end_ns or 0)
    loaded = injector.begin(Fault(at_s=5, kind="background", duration_s=1))
    injector.end(loaded)
    assert loaded.restarts == []


def test_capacity_and_trace_faults_change_the_cells_capacity_and_restore_it(tmp_path: Path) -> None:
    events: list[dict[str, Any]] = []
    injector = FaultInjector(_NoProcs(), events.append, bus=None, uplink_mbps=81.3)  # type: ignore[arg-type]
    window = injector.begin(Fault(at_s=15, kind="capacity", duration_s=15, uplink_mbps=50))
    injector.end(window)
    trace = tmp_path / "dip.mahi"
    trace.write_text("\n".join(str(ms) for ms in range(1, 101)) + "\n")
    injector.end(injector.begin(Fault(at_s=1, kind="trace", duration_s=5, file=str(trace))))
    assert events == [
        {"kind": "capacity", "uplink_mbps": 50.0},
        {"kind": "capacity", "uplink_mbps": 81.3},
        {"kind": "trace", "file": str(trace.resolve()), "mean_mbps": 0.0},
        {"kind": "capacity", "uplink_mbps": 81.3},  # also ends the trace
    ]
    with pytest.raises(ConfigError, match="file"):
        Fault(at_s=1, kind="trace")
    drop = builtin_scenario("capacity-drop")
    assert [(f.kind, f.uplink_mbps) for f in drop.faults] == [("capacity", 50.0)]


def test_outcome_says_what_the_drone_saw_and_did_while_a_fault_lasted() -> None:
    s = 1_000_000_000
    window = FaultWindow(Fault(at_s=10, kind="capacity", duration_s=2), 0.0, 10 * s)
    window.end_wall, window.end_ns = 2.0, 12 * s
    statuses = [
        replace(_status(10 * s, 20.0), rtt_samples_ms=(20.0, 40.0)),
        replace(_status(11 * s, 20.0), state="q6", camera_rate_factor=0.5, rtt_samples_ms=(60.0,)),
        replace(_status(12 * s, 20.0), state="q6", camera_rate_factor=0.5, rtt_samples_ms=(30.0,)),
        # after it ended: not counted as during it, but the window's last signals
        replace(_status(13 * s, 20.0), rtt_samples_ms=(500.0,), latency="HL", t_cam_ms=80.0),
    ]
    errors = [(9 * s, 3.0), (10 * s, 0.02), (11 * s, 0.4), (22 * s + 1, 0.9)]  # before, in, in, settled
    got = outcome(window, [], statuses, next_start_ns=None, tracking_errors=errors)
    assert got["max_tracking_error_m"] == 0.4
    assert outcome(window, [], statuses, next_start_ns=None)["max_tracking_error_m"] is None
    assert got["rtt_ms_during"]["mean"] == pytest.approx(37.5)
    assert got["states_s_during"] == {"q1": 1.0, "q6": 1.0}
    assert got["camera_slowed_after_s"] == pytest.approx(1.0)
    # Why a drone not back at the edge is not: the last signals the window saw (here after the fault).
    assert got["at_window_end"] == {
        "state": "q1", "latency": "HL", "t_cam_ms": 80.0, "t_cc_ms": None, "p_cam": 0.0, "p_cc": 0.0,
        "risk": "LR",
    }  # fmt: skip


def _check(result: dict[str, Any], kinds_with_fallback: set[str]) -> None:
    for fault in result["faults"]:
        kind = fault["kind"]
        assert fault["recovered"], fault
        assert fault["max_setpoint_gap_ms"] is not None
        # setpoints to the FC never paused as long as the watchdog (how steady they are: a benchmark's
        # target, bench/supervisor_reaction.py)
        assert fault["max_setpoint_gap_ms"] < T_WD_MS, fault
        if kind in kinds_with_fallback:
            assert fault["fallback"], fault
            if fault["fallback_at_start"]:
                continue  # an earlier fault's fallback was still flying it: nothing to time here
            assert fault["fallback_after_last_command_ms"] <= T_WD_MS + TICK_MS + 15, fault
            assert fault["log"], fault  # a line that names what happened


@pytest.mark.slow
@pytest.mark.timeout(600)  # a flight that failed while starved is flown again
def test_faults_flight_falls_back_in_time_and_recovers(tmp_path: Path) -> None:
    """The shipped faults scenario, as docs/reliability.md measures it: MPC and router killed, coverage
    lost for 0.5, 2 and 10 s, the downlink lost, the FC silent for 2 s, the detector flooded."""
    scenario = builtin_scenario("faults")
    assert {f.kind for f in scenario.faults} == {
        "mpc_kill", "router_kill", "coverage_loss", "downlink_loss", "fc_silence", "detector_flood",
    }  # fmt: skip
    fly_for_behaviour(lambda out: run_scenario(scenario, out, progress=False), tmp_path, _check_faults)


def _check_faults(result: dict[str, Any], _: Path) -> None:
    _check(result, {"mpc_kill", "coverage_loss", "downlink_loss", "router_kill"})
    by_kind = {f["kind"]: f for f in result["faults"]}
    assert sorted(f["duration_s"] for f in result["faults"] if f["kind"] == "coverage_loss") == [0.5, 2, 10]
    assert any("no state from the flight controller" in line for line in by_kind["fc_silence"]["log"])
    assert "flood frames sent" in by_kind["detector_flood"]["notes"][0]
    # The flood is CPU load: on a starved machine it reaches control; with headroom it costs frames only.
    if not starved(result):
        assert not by_kind["detector_flood"]["fallback"]


@pytest.mark.slow
@pytest.mark.timeout(600)  # a flight that failed while starved is flown again
def test_replica_faults_never_send_the_drone_to_its_fallback(tmp_path: Path) -> None:
    """The shipped replicas scenario: two MPC and two planner replicas; the MPC replica flying the drone
    killed, a third joining, the one flying hung for 2 s, the planner replica publishing killed, the
    active QoS agent killed and then hung. None of them makes the drone fall back or leave its mission
    (docs/reliability.md)."""
    scenario = builtin_scenario("replicas")
    assert [f.kind for f in scenario.faults] == [
        "mpc_replica_kill", "replica_join", "mpc_replica_hang", "planner_replica_kill", "background",
        "qos_agent_kill", "qos_agent_hang",
    ]  # fmt: skip
    fly_for_behaviour(lambda out: run_scenario(scenario, out, progress=False), tmp_path, _check_replicas)


def _check_replicas(result: dict[str, Any], _: Path) -> None:
    _check(result, set())
    for fault in result["faults"]:
        assert not fault["fallback"], fault
        assert fault["max_tracking_error_m"] < 0.5, fault  # it kept flying the mission, not a stale end
    kill, join, hang, planner, _background, agent, agent_hang = result["faults"]
    assert "served the drone" in planner["notes"][0], planner
    # the standby QoS agent told the drone its grant within 2 s, with the session it adopted
    assert agent["notes"][0].endswith("was the active agent"), agent
    grant = agent["grant"]
    assert grant["before"] == "available", grant  # the background load: the drone held a session
    assert grant["after"] == "available", grant
    assert grant["same_session"], grant
    assert grant["served_after_s"] < 2.0, grant
    # the agent that took over, hung: the restarted one serves once the hung one's lease (2 s) ran out
    assert agent_hang["notes"][0].endswith("was the active agent"), agent_hang
    grant = agent_hang["grant"]
    assert (grant["before"], grant["after"], grant["same_session"]) == ("available", "available", True), grant
    # the router counts the 2 s lease from the hung agent's last keep-alive (sent every lease / 4)
    assert 1.4 <= grant["served_after_s"] < 3.5, grant
    sessions = result["qos_network"]["sessions"]
    assert (sessions["conflicts"], sessions["open_at_end"]) == (0, 0), sessions
    assert "served the drone" in kill["notes"][0], kill  # it acted on the replica flying the drone
    assert "served the drone" in hang["notes"][0], hang
    assert join["notes"] == ["mpc-join1 joined"]


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_soak_ten_minutes_with_the_load_toggling(tmp_path: Path) -> None:
    """The soak: 600 s, or DYNQOS_SOAK_S seconds (CI flies 90, one load period and 30 s of memory
    after the first minute, to keep the whole run inside 50 minutes on two cores)."""
    soak = builtin_scenario("soak")
    seconds = float(os.environ.get("DYNQOS_SOAK_S", soak.duration_s))
    soak = replace(soak, duration_s=seconds, faults=tuple(f for f in soak.faults if f.at_s + 30 <= seconds))
    result = run_scenario(soak, tmp_path, progress=False)
    assert result["ok"], result["failure"]
    for name, mb in result["memory_mb"].items():
        # Bounded memory: after a minute of warm-up no process grows by more than 20 MB (+10%), neither in
        # what it has resident nor in what it allocated itself (where a leak would show).
        for prefix in ("", "anon_"):
            after_1min = mb[f"{prefix}after_1min"]
            settled = after_1min if after_1min is not None else mb[f"{prefix}first"]
            assert mb[f"{prefix}max"] - settled < 20 + 0.1 * settled, (name, prefix, mb)
    onsets = len(soak.faults)
    to_priority = [t for t in result["transitions"] if t["to"] in ("q2", "q3", "q4", "q5", "q6")]
    assert len(to_priority) >= onsets, result["transitions"]  # the supervisor cycles with the load
    assert result["setpoint_gap_max_ms"] < T_WD_MS


def test_the_report_says_when_a_fault_found_the_drone_in_its_fallback() -> None:
    from dynqos.reports.markdown import _fault_lines

    fault = {
        "kind": "coverage_loss",
        "at_s": 20,
        "duration_s": 2,
        "rtt_ms_during": {},
        "states_s_during": {"qA": 2.0},
        "camera_slowed_after_s": None,
        "fallback": True,
        "fallback_at_start": True,
        "max_tracking_error_m": None,
    }
    (found,) = _fault_lines({"faults": [fault]})
    assert found.endswith("; fallback True (already at its start)"), found
    (caused,) = _fault_lines({"faults": [{**fault, "fallback_at_start": False}]})
    assert caused.endswith("; fallback True"), caused
