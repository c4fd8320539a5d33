"""MPC replicas over real processes: the one flying the drone is killed, then a new replica joins, then
the one flying is hung (SIGSTOP); the drone never falls back to its PID (docs/reliability.md)."""

from __future__ import annotations

import itertools
import re
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.keys import Downlink
from dynqos.common.messages import Command, State
from dynqos.common.transport import Priority
from tests.procs import DynqosProcess
from tests.test_onboard_loop import LoopProcs, Observer, edge_loop, mpc_replica

pytestmark = [pytest.mark.integration]

WATCHDOG_MS = {"states": 150, "copies": 250}  # the drone's watchdog: its default, and what copies need


@pytest.fixture
def edge(
    tmp_path: Path, request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> Iterator[LoopProcs]:
    """The loop with two MPC replicas; what a standby reads (`[mpc] standby_reads`) is the parameter,
    and the holder's copies go with the drone watchdog they need (docs/reliability.md)."""
    reads = getattr(request, "param", "states")
    monkeypatch.setenv("DYNQOS_MPC__STANDBY_READS", reads)
    monkeypatch.setenv("DYNQOS_SUPERVISOR__WATCHDOG_S", str(WATCHDOG_MS[reads] / 1000))
    with edge_loop(tmp_path, ("mpc-a", "mpc-b")) as started:
        yield started


def _followed(observer: Observer, condition: Callable[[State], bool], timeout_s: float, what: str) -> State:
    found: list[State] = []

    def check(state: State) -> bool:
        if condition(state):
            found.append(state)
            return True
        return False

    assert observer.wait_until(check, timeout_s), f"{what}: never seen in {timeout_s} s"
    return found[0]


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("edge", "qos"),
    [("states", "default"), ("states", "priority"), ("copies", "dynamic")],
    indirect=["edge"],
)
def test_killing_hanging_and_adding_mpc_replicas_never_sends_the_drone_to_its_fallback(
    edge: LoopProcs, qos: str, request: pytest.FixtureRequest
) -> None:
    """In each QoS mode: the drone's states and the commands take that mode's flows. The standby reads
    the drone's own states, and in the dynamic mode the holder's copies (the dynamic mode with the
    drone's own states is the shipped `replicas` scenario's, tests/test_faults.py: the same kill, join
    and hang)."""
    config, zcfg, procs = edge
    observer = Observer(zcfg)
    try:
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config, env={"DYNQOS_ONBOARD__QOS": qos})
        first = _followed(observer, lambda s: s.mode == "offboard" and s.command_term > 0, 60, "offload")
        observer.wait_until(lambda s: False, 4.0)  # settle on the circle
        serving = observer.state_log[-1].command_replica
        assert serving in ("mpc-a", "mpc-b"), serving
        term = observer.state_log[-1].command_term

        # 1. SIGKILL the replica that flies the drone: its token goes, the other takes over.
        procs[serving].proc.kill()
        standby = "mpc-b" if serving == "mpc-a" else "mpc-a"
        after_kill = _followed(observer, lambda s: s.command_replica == standby, 5, f"{standby} flying")
        assert after_kill.command_term > term
        procs.pop(serving).stop()
        observer.wait_until(lambda s: False, 3.0)

        # 2. A new replica joins mid-flight: the drones it ranks first move to it (or stay), no fallback.
        procs["mpc-c"] = mpc_replica("mpc-c", config)
        observer.wait_until(lambda s: False, 4.0)
        flying = observer.state_log[-1].command_replica
        assert flying in ("mpc-c", standby)

        # 3. SIGSTOP the replica that flies it: its token stays, its silence hands the drone over.
        term = observer.state_log[-1].command_term
        procs[flying].proc.send_signal(signal.SIGSTOP)
        try:
            other = "mpc-c" if flying == standby else standby
            after_hang = _followed(observer, lambda s: s.command_replica == other, 5, f"{other} flying")
            assert after_hang.command_term > term
            observer.wait_until(lambda s: False, 2.0)
        finally:
            procs[flying].proc.send_signal(signal.SIGCONT)
        observer.wait_until(lambda s: False, 3.0)
        assert observer.state_log[-1].mode == "offboard"

        # 4. Commands with a replaced replica's term, answering a real state: refused, never flown.
        latest = observer.state_log[-1]
        stale = Command(uav="uav1", seq=latest.seq, state_seq=latest.seq, state_stamp_ns=latest.stamp_ns,
                        edge_hold_ns=0, dt_s=0.05, accel_mps2=((9.0, 0.0, 0.0),) * 10, yaw_rad=(0.0,) * 10,
                        term=1, replica="mpc-a")  # fmt: skip
        attacker = observer.bus.publisher(keys.downlink("uav1", Downlink.COMMAND), Priority.REAL_TIME)
        for _ in range(5):
            attacker.put(stale)
        observer.wait_until(lambda s: False, 2.0)
        assert first.command_term >= 1
    finally:
        observer.bus.close()
    log = procs.pop("onboard").stop()
    mpc_logs = {name: procs.pop(name).stop() for name in [n for n in procs if n.startswith("mpc-")]}
    for name, text in mpc_logs.items():  # what each replica did, then what the drone followed
        print(name, *re.findall(r".*(?:drone uav1: |is late: ).*", text), sep="\n  ")
    print(*re.findall(r".*controller is now .*", log), sep="\n")
    assert "fallback PID" not in log, re.findall(r".*fallback PID.*", log)[:3]
    assert log.count("controller is now MPC replica") >= 2
    command_gap = max(float(g) for g in re.findall(r"max_command_gap_ms=([\d.]+)", log))
    setpoint_gap = max(float(g) for g in re.findall(r"max_setpoint_gap_ms=([\d.]+)", log))
    print(
        f"longest gap between accepted commands {command_gap:.0f} ms, between setpoints {setpoint_gap:.0f} ms"
    )
    reads = request.node.callspec.params["edge"]
    assert command_gap < WATCHDOG_MS[reads]
    assert setpoint_gap < WATCHDOG_MS[reads]  # steadiness: bench/supervisor_reaction.py
    assert any("took over" in text for text in mpc_logs.values()), mpc_logs
    assert all(f"standby_reads={reads} " in text for text in mpc_logs.values())
    assert int(re.findall(r" fenced=(\d+)", log)[-1]) >= 5  # the stale terms were refused
    assert "refused a command from MPC replica" in log  # logged once (the hung replica may come first)


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("qos", ["default", "priority"])
def test_killing_the_planner_replica_that_publishes_continues_the_mission_from_the_other(
    tmp_path: Path, qos: str
) -> None:
    """Two planners; the one publishing the drone's references is SIGKILLed: the other continues the
    same mission from where it was (no restart at mission time 0) and the drone follows it; the killed
    one comes back, takes the drone back (it ranks first) and goes on from the same mission time. On
    each flow: the drone's states (which the planners follow) take that mode's flow. The dynamic mode
    moves them between these two; its planner kill is the shipped `replicas` scenario's
    (tests/test_faults.py)."""
    with edge_loop(tmp_path) as (config, zcfg, procs):
        procs["planner-b"] = DynqosProcess(
            ["edge", "planner"], config, env={"DYNQOS_PLANNER__REPLICA_ID": "planner-b"}
        )
        observer = Observer(zcfg)
        try:
            env = {"DYNQOS_ONBOARD__QOS": qos}
            procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config, env=env)
            _followed(observer, lambda s: s.mode == "offboard", 60, "offload")
            observer.wait_until(lambda s: False, 4.0)
            observer.collect()
            publishing = observer.ref_log[-1].replica
            before = observer.ref_log[-1].mission_t_s
            victim = "planner-b" if publishing == "planner-b" else "planner"
            procs[victim].proc.kill()
            killed_ns = time.monotonic_ns()
            procs.pop(victim).stop()  # reaped
            observer.wait_until(lambda s: False, 4.0)
            observer.collect()
            after = [r for r in observer.ref_log if r.replica and r.replica != publishing]
            assert after, "the other planner never published"
            went_on = f"{after[0].replica} went on at {after[0].mission_t_s:.2f} s"
            print(f"planner {publishing} killed at mission time {before:.2f} s; {went_on}")
            assert before < after[0].mission_t_s < before + 2.0  # continued, not restarted
            assert after[-1].term > observer.ref_log[0].term
            # the drone flies the new planner's references (past the old ones' horizon), not the old
            _tracks(observer, killed_ns + 1_500_000_000, "after the kill")

            env = {"DYNQOS_PLANNER__REPLICA_ID": publishing}  # the same replica, back
            procs[victim] = DynqosProcess(["edge", "planner"], config, env=env)
            back_ns = time.monotonic_ns()
            observer.wait_until(lambda s: False, 6.0)
            observer.collect()
            went_back = [
                [(r.replica, r.term, round(r.mission_t_s, 3)) for r in pair]
                for pair in itertools.pairwise(observer.ref_log)
                if pair[1].mission_t_s < pair[0].mission_t_s
            ]
            assert not went_back, f"a planner restarted the mission: {went_back[:3]}"
            _tracks(observer, back_ns, "after the restart")
        finally:
            observer.bus.close()
        log = procs.pop("onboard").stop()
    assert "fallback PID" not in log, re.findall(r".*fallback PID.*", log)[:3]
    setpoint_gap = max(float(g) for g in re.findall(r"max_setpoint_gap_ms=([\d.]+)", log))
    assert setpoint_gap < WATCHDOG_MS["states"]  # steadiness: bench/supervisor_reaction.py


def _tracks(observer: Observer, since_ns: int, when: str) -> None:
    """The drone stays on the latest published reference (a few tens of cm on the circle)."""
    errors = observer.tracking_errors(since_ns)
    assert len(errors) > 40, f"{when}: {len(errors)} states"
    print(f"{when}: worst tracking error {max(errors) * 100:.0f} cm over {len(errors)} states")
    assert max(errors) < 0.5, f"{when}: the drone left the mission by {max(errors):.2f} m"
