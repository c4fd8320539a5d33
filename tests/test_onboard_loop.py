"""The whole loop on 127.0.0.1: simulator, router, planner, MPC and the onboard daemon as real processes."""

from __future__ import annotations

import contextlib
import math
import re
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import (
    CameraFrame,
    Command,
    Message,
    Reference,
    State,
    SupervisorStatus,
    decode,
    encode,
)
from dynqos.common.modes import ControlSource, Flow
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus
from dynqos.edge.detector.assembler import FrameAssembler
from dynqos.edge.detector.circles import decode_depth
from dynqos.reports.measures import reference_errors
from tests.conftest import flow_ports
from tests.procs import DynqosProcess
from tests.test_vehicle_mavlink import free_udp_port

pytestmark = [pytest.mark.integration]


def loop_config(tmp_path: Path, zcfg: ZenohConfig, extra: str = "") -> Path:
    api = free_udp_port()
    config = tmp_path / "loop.toml"
    config.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        f"[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\noffboard_remote_port = {api}\n"
        f"gcs_remote_port = {free_udp_port()}\n"
        f'[onboard]\nmavlink_url = "udpin:127.0.0.1:{api}"\ncamera_fps = 5\nhealth_interval_s = 1\n'
        "[planner]\nlead_in_s = 3\n" + extra
    )
    return config


class Observer:
    """Listens to the drone's states and the planner's references like a ground station would."""

    def __init__(self, zcfg: ZenohConfig) -> None:
        self.bus = open_bus(zcfg, Role.EDGE)
        self.states: BoundedQueue[Received] = BoundedQueue(100_000)
        self.refs: BoundedQueue[Received] = BoundedQueue(100_000)
        self.cmds: BoundedQueue[Received] = BoundedQueue(100_000)
        self.bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATE), self.states)
        self.bus.subscribe(keys.downlink("uav1", Downlink.REFERENCE), self.refs)
        self.bus.subscribe(keys.downlink("uav1", Downlink.COMMAND), self.cmds)
        self.state_log: list[State] = []
        self.ref_log: list[Reference] = []

    def collect(self) -> None:
        self.state_log += [i.message for i in self.states.drain() if isinstance(i.message, State)]
        self.ref_log += [i.message for i in self.refs.drain() if isinstance(i.message, Reference)]

    def tracking_errors(self, since_ns: int) -> list[float]:
        """Distance from each state to the reference sample due at its stamp (same host clock)."""
        self.collect()
        return [error for stamp, error in reference_errors(self.state_log, self.ref_log) if stamp >= since_ns]

    def wait_until(self, predicate: object, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            item = self.states.get(0.5)
            if item is not None and isinstance(item.message, State):
                self.state_log.append(item.message)
                if predicate(item.message):  # type: ignore[operator]
                    return True
        return False


LoopProcs = tuple[Path, ZenohConfig, dict[str, DynqosProcess]]


def mpc_replica(name: str, config: Path) -> DynqosProcess:
    """An MPC process; named replicas (not "mpc") get that replica id (docs/reliability.md)."""
    return DynqosProcess(
        ["edge", "mpc"], config, env=None if name == "mpc" else {"DYNQOS_MPC__REPLICA_ID": name}
    )


@contextlib.contextmanager
def edge_loop(
    tmp_path: Path, mpcs: tuple[str, ...] = ("mpc",), vehicle_env: dict[str, str] | None = None
) -> Iterator[LoopProcs]:
    """Router, simulator, planner and the MPC processes `mpcs`; the test adds the onboard daemon. Each is
    stopped at the end in the reverse order of its start (a SIGSTOPped one is resumed first).
    `vehicle_env`: settings for the simulator (DYNQOS_VEHICLE__...)."""
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg)
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router"] = DynqosProcess(["edge", "router"], config)
        procs["vehicle"] = DynqosProcess(["sim", "vehicle", "--duration", "600"], config, env=vehicle_env)
        procs["planner"] = DynqosProcess(["edge", "planner"], config)
        for name in mpcs:
            procs[name] = mpc_replica(name, config)
        yield config, zcfg, procs
    finally:
        for name in reversed(list(procs)):
            procs[name].proc.send_signal(signal.SIGCONT)
            procs[name].stop()


@pytest.fixture
def loop(tmp_path: Path) -> Iterator[LoopProcs]:
    with edge_loop(tmp_path) as started:
        yield started


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_drone_flies_the_circle_survives_bad_commands_and_an_mpc_restart(
    loop: tuple[Path, ZenohConfig, dict[str, DynqosProcess]],
) -> None:
    config, zcfg, procs = loop
    observer = Observer(zcfg)
    try:
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config)
        assert observer.wait_until(lambda s: s.mode == "offboard", 60), "the drone never started offloading"
        started = time.monotonic_ns()
        # Lead-in (3 s) and the first lap (10 s), then measure one more lap.
        observer.wait_until(lambda s: False, 13.0)
        lap_start = time.monotonic_ns()
        observer.wait_until(lambda s: False, 10.0)
        errors = observer.tracking_errors(lap_start)
        rmse = math.sqrt(sum(e * e for e in errors) / len(errors))
        print(f"circle RMSE over the second lap: {rmse * 100:.1f} cm from {len(errors)} states")
        assert len(errors) > 150
        assert rmse < 0.15
        assert started < lap_start

        # Adversarial commands: garbage, a replay of a real command, a forged one for an unknown state.
        observer.collect()
        real = [i.message for i in observer.cmds.drain() if isinstance(i.message, Command)]
        assert real
        attacker = observer.bus.publisher(keys.downlink("uav1", Downlink.COMMAND), Priority.REAL_TIME)
        forged = Command(
            uav="uav1",
            seq=10**9,
            state_seq=10**9,
            state_stamp_ns=time.monotonic_ns(),
            edge_hold_ns=0,
            dt_s=0.05,
            accel_mps2=[(9.0, 0.0, 0.0)] * 5,
            yaw_rad=[0.0] * 5,
            term=real[-1].term,  # a forger that copies the MPC's term still answers no state we sent
            replica=real[-1].replica,
        )
        for _ in range(5):
            attacker.put_bytes(b"\x00garbage")
            attacker.put_bytes(encode(real[0]))  # a replay
            attacker.put(forged)
        observer.wait_until(lambda s: False, 2.0)

        # The MPC dies: fallback at once, the drone holds; it comes back: offload resumes.
        procs["mpc"].stop()
        observer.wait_until(lambda s: False, 3.0)
        last_command = max(i.arrival_ns for i in observer.cmds.drain())
        # Where it was when the fallback took over: T_wd after the last command.
        switch = next(s for s in observer.state_log if s.stamp_ns >= last_command + 150_000_000)
        held = [s for s in observer.state_log if s.stamp_ns >= switch.stamp_ns]
        drift = max(np.linalg.norm(np.array(s.pos_m) - np.array(switch.pos_m)) for s in held)
        print(f"largest distance from where the fallback took over: {drift:.2f} m")
        assert drift < 0.5
        procs["mpc"] = DynqosProcess(["edge", "mpc"], config)
        observer.wait_until(lambda s: False, 4.0)

        # The flight controller goes silent for 2 s (our own child, paused by its pid), then comes back.
        procs["vehicle"].proc.send_signal(signal.SIGSTOP)
        try:
            observer.wait_until(lambda s: False, 2.0)
        finally:
            procs["vehicle"].proc.send_signal(signal.SIGCONT)
        observer.wait_until(lambda s: False, 4.0)
    finally:
        observer.bus.close()
    log = procs.pop("onboard").stop()
    fallback = re.findall(r"fallback PID holding position \(watchdog: last valid command (\d+) ms ago\)", log)
    assert fallback, log[-3000:]
    # The MPC's death is the flight's first fallback: T_wd + one 20 ms tick (+ scheduling slack). (After
    # the FC's 2 s silence the watchdog line says ~2000 ms: no state went up, so no command came down.)
    assert int(fallback[0]) <= 150 + 20 + 15
    assert log.count("control from the edge") >= 3  # offload resumed after the MPC and after the FC came back
    assert "no state from the flight controller" in log
    assert "the flight controller's state is back" in log
    health = re.findall(r"unknown=(\d+) expired=\d+ future=\d+ wrong_drone=\d+", log)[-1]
    assert int(health) >= 5  # the replays and the forged commands were rejected
    assert re.findall(r"rejected=(\d+)", log)[-1] != "0"
    gaps = [float(g) for g in re.findall(r"max_setpoint_gap_ms=([\d.]+)", log)]
    assert max(gaps) < 100  # setpoints to the FC never paused longer than 100 ms


@pytest.mark.timeout(120)
def test_onboard_streams_the_real_frames_from_files_without_taking_off(
    tmp_path: Path, shared_data: Path
) -> None:
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg, extra="")
    text = config.read_text().replace(
        "camera_fps = 5\n", f'camera_fps = 10\ncamera = "files"\nfiles_dir = "{shared_data / "rgbd"}"\n'
    )
    config.write_text(text)
    router = DynqosProcess(["edge", "router"], config)
    bus = open_bus(zcfg, Role.EDGE)
    frames: BoundedQueue[Received] = BoundedQueue(100)
    states: BoundedQueue[Received] = BoundedQueue(100)
    bus.subscribe(keys.uplink_any_flow("uav1", Stream.CAMERA_DEPTH), frames)
    bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATE), states)
    onboard = DynqosProcess(["onboard"], config)  # no --takeoff: it must never arm
    try:
        got = [frames.get(20) for _ in range(6)]
    finally:
        log = onboard.stop()
        bus.close()
        router.stop()
    assert all(item is not None for item in got)
    sizes = {(i.message.width, i.message.height, i.message.encoding) for i in got if i}  # type: ignore[attr-defined]
    assert sizes == {(640, 480, "zstd16")}
    assert states.get(0) is None  # no flight controller, no state
    assert "not taking off" in log


@pytest.mark.timeout(120)
def test_onboard_paces_each_image_in_parts_that_the_detector_joins(tmp_path: Path, shared_data: Path) -> None:
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg)
    pace_mbps, part_bytes = 20.0, 16384
    config.write_text(
        config.read_text().replace(
            "camera_fps = 5\n",
            f'camera_fps = 2\ncamera = "files"\nfiles_dir = "{shared_data / "rgbd"}"\n'
            f"camera_pace_mbps = {pace_mbps}\ncamera_part_bytes = {part_bytes}\n",
        )
    )
    router = DynqosProcess(["edge", "router"], config)
    bus = open_bus(zcfg, Role.EDGE)
    parts: BoundedQueue[Received] = BoundedQueue(10_000)
    bus.subscribe(keys.uplink_any_flow("uav1", Stream.CAMERA_DEPTH), parts)
    onboard = DynqosProcess(["onboard"], config)
    assembler = FrameAssembler()
    arrivals: dict[int, list[int]] = {}
    whole: list[CameraFrame] = []
    try:
        while len(whole) < 2:
            item = parts.get(20)
            assert item is not None, "no camera parts arrived"
            assert isinstance(item.message, CameraFrame)
            arrivals.setdefault(item.message.seq, []).append(item.arrival_ns)
            done = assembler.add(item.message)
            if done is not None:
                whole.append(done)
    finally:
        onboard.stop()
        bus.close()
        router.stop()
    for frame in whole:
        assert decode_depth(frame).shape == (480, 640)  # the parts make the real image again
        assert len(arrivals[frame.seq]) == math.ceil(len(frame.payload) / part_bytes)
        span_s = (arrivals[frame.seq][-1] - arrivals[frame.seq][0]) / 1e9
        paced_s = (len(frame.payload) - part_bytes) * 8 / (pace_mbps * 1e6)
        assert span_s >= 0.8 * paced_s  # spread over time at the pace, not handed over in one burst


@pytest.mark.timeout(60)
def test_onboard_speaks_sd_notify_ready_watchdog_and_stopping(tmp_path: Path) -> None:
    """What systemd's Type=notify and WatchdogSec (deploy/systemd/dynqos-onboard.service) rely on."""
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg, extra="")
    config.write_text(config.read_text().replace("camera_fps = 5\n", 'camera = "none"\n'))
    notify_path = tmp_path / "notify.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(str(notify_path))
        notify.settimeout(15)
        router = DynqosProcess(["edge", "router"], config)
        onboard = DynqosProcess(
            ["onboard"], config, env={"NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}
        )
        try:
            got = [notify.recv(4096).decode() for _ in range(3)]
            assert got[0] == "READY=1"
            assert got[1:] == ["WATCHDOG=1", "WATCHDOG=1"]  # fed at half of WATCHDOG_USEC by the loop
            onboard.proc.terminate()
            while (text := notify.recv(4096).decode()) != "STOPPING=1":
                assert text == "WATCHDOG=1" or text.startswith("STATUS=")
        finally:
            onboard.stop()
            router.stop()


@pytest.mark.slow
@pytest.mark.timeout(240)
@pytest.mark.parametrize("qos", ["priority", "default", "dynamic"])
def test_fc_silence_in_every_qos_mode_holds_position_and_resumes_at_the_edge(
    loop: tuple[Path, ZenohConfig, dict[str, DynqosProcess]], qos: str
) -> None:
    """An early version crashed here with a fixed flow: the FC's silence became a status the decoder refused.

    The vehicle (our own child) is paused by its pid for 2 s mid-flight: the daemon must keep running,
    report the hold in its status, keep the setpoint stream alive and hand control back to the edge."""
    config, zcfg, procs = loop
    observer = Observer(zcfg)
    status: BoundedQueue[Received] = BoundedQueue(100_000)
    observer.bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATUS), status, expect=(SupervisorStatus,))

    def statuses() -> list[SupervisorStatus]:
        return [i.message for i in status.drain() if isinstance(i.message, SupervisorStatus)]

    seen: list[SupervisorStatus] = []

    def wait_for(source: ControlSource, after_ns: int, timeout_s: float) -> SupervisorStatus | None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            observer.wait_until(lambda s: False, 0.2)
            seen.extend(statuses())
            hit = [s for s in seen if s.control_source is source and s.control_changed_ns > after_ns]
            if hit:
                return hit[0]
        return None

    try:
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff", "--set", f"onboard.qos={qos}"], config)
        assert observer.wait_until(lambda s: s.mode == "offboard", 60), "the drone never started offloading"
        assert wait_for(ControlSource.EDGE, 0, 15), "the edge never took control"
        observer.wait_until(lambda s: False, 2.0)
        silence_ns = time.monotonic_ns()
        procs["vehicle"].proc.send_signal(signal.SIGSTOP)
        try:
            hold = wait_for(ControlSource.HOLD, silence_ns, 2.0)
        finally:
            procs["vehicle"].proc.send_signal(signal.SIGCONT)
        resumed_ns = time.monotonic_ns()
        back = wait_for(ControlSource.EDGE, resumed_ns, 15)
        alive = procs["onboard"].alive()
    finally:
        observer.bus.close()
    log = procs.pop("onboard").stop()
    assert alive, log[-3000:]
    assert "Traceback" not in log
    assert hold is not None, log[-3000:]
    assert 450 <= (hold.control_changed_ns - silence_ns) / 1e6 <= 700  # STALE_STATE_NS after the last state
    assert {s.flow for s in seen if s.stamp_ns >= silence_ns} <= (
        {Flow(qos)} if qos != "dynamic" else {Flow.DEFAULT, Flow.PRIORITY}
    )
    assert back is not None, log[-3000:]
    gaps = [s.setpoint_gap_ms for s in seen if s.setpoint_gap_ms is not None and s.stamp_ns >= silence_ns]
    assert gaps
    assert max(gaps) < 100, gaps  # the setpoint stream never paused: PX4 would leave offboard
    assert "no state from the flight controller" in log
    assert "the flight controller's state is back" in log


@pytest.mark.timeout(120)
@pytest.mark.parametrize("qos", ["default", "priority", "dynamic"])
def test_the_status_counts_every_uplink_byte_the_drone_hands_to_zenoh(tmp_path: Path, qos: str) -> None:
    """`uav_offered_mbps` rests on the status's `uplink_bytes`: every message the drone puts (state,
    status, QoS request, camera), not the camera's bytes alone. With the camera off, a count of camera
    bytes would read 0; the count must match what a subscriber to all of the drone's uplink receives."""
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg, extra="")
    config.write_text(config.read_text().replace("camera_fps = 5\n", 'camera = "none"\n'))
    got: list[tuple[int, object]] = []  # (encoded size, message) in arrival order
    statuses = 0
    lock = threading.Lock()
    enough = threading.Event()

    def sized(data: bytes) -> Message:
        nonlocal statuses
        message = decode(data)
        with lock:
            got.append((len(data), message))
            statuses += isinstance(message, SupervisorStatus)
            if statuses >= 16:
                enough.set()
        return message

    procs: list[DynqosProcess] = []
    bus = None
    log = ""
    try:
        procs.append(DynqosProcess(["edge", "router"], config))
        procs.append(DynqosProcess(["sim", "vehicle", "--duration", "120"], config))
        bus = open_bus(zcfg, Role.EDGE)
        bus.subscribe("dynqos/uav1/up/**", BoundedQueue(100_000), decoder=sized)
        onboard = DynqosProcess(["onboard", "--set", f"onboard.qos={qos}"], config)  # no takeoff: states only
        procs.append(onboard)
        assert enough.wait(60), "the drone sent fewer than 16 statuses in 60 s"
    finally:
        if len(procs) == 3:
            log = procs.pop().stop()
        if bus is not None:
            bus.close()
        for proc in reversed(procs):
            proc.stop()
    with lock:
        rows = list(got)
    marks = [k for k, (_, m) in enumerate(rows) if isinstance(m, SupervisorStatus)]
    first, last = marks[2], marks[-1]  # past the start, where the sessions were still matching
    a, b = rows[first][1], rows[last][1]
    assert isinstance(a, SupervisorStatus)
    assert isinstance(b, SupervisorStatus)
    counted = b.uplink_bytes - a.uplink_bytes
    received = sum(size for size, _ in rows[first:last])  # from status a (sent after its count) to b
    assert b.camera_bytes == 0, log[-2000:]
    assert counted > 0, log[-2000:]
    print(f"{qos}: counted {counted} B, received {received} B between two statuses")
    assert counted == pytest.approx(received, rel=0.1)
    if qos != "dynamic":
        assert {m.flow for _, m in rows if isinstance(m, SupervisorStatus)} == {Flow(qos)}
