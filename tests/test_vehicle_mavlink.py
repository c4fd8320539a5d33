"""The simulator as a real process speaking MAVLink over UDP on 127.0.0.1 to a pymavlink client."""

from __future__ import annotations

import itertools
import selectors
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common.geometry import yaw_of
from dynqos.experiment.processes import free_port
from dynqos.onboard.fclink import IGNORE_YAW, POSITION_AND_YAW_MASK, FcLink
from tests.procs import DYNQOS, DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def free_udp_port() -> int:
    return free_port(socket.SOCK_DGRAM)


class VehicleProcess(DynqosProcess):
    def __init__(self, tmp_path: Path, offboard_port: int, gcs_port: int) -> None:
        config = tmp_path / "vehicle.toml"
        config.write_text(
            f"[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\n"
            f"offboard_remote_port = {offboard_port}\ngcs_remote_port = {gcs_port}\n"
        )
        super().__init__(["sim", "vehicle", "--duration", "300"], config)


@pytest.fixture
def vehicle(tmp_path: Path) -> Iterator[tuple[VehicleProcess, Any]]:
    port = free_udp_port()
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    proc = VehicleProcess(tmp_path, port, free_udp_port())
    try:
        assert client.wait_heartbeat(timeout=10) is not None
        yield proc, client
    finally:
        client.close()
        proc.stop()


def command(client: Any, cmd: int, *params: float) -> int:
    p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
    client.mav.command_long_send(1, 1, cmd, 0, *p)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        ack = client.recv_match(type="COMMAND_ACK", blocking=True, timeout=1)
        if ack is not None and ack.command == cmd:
            result: int = ack.result
            return result
    raise AssertionError(f"no COMMAND_ACK for {cmd}")


def wait_for(client: Any, predicate: Any, kind: str, timeout_s: float) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = client.recv_match(type=kind, blocking=True, timeout=1)
        if msg is not None and predicate(msg):
            return msg
    raise AssertionError(f"no {kind} matching within {timeout_s} s")


def send_setpoint(client: Any, x: float, y: float, z: float, yaw: float = 0.0, mask: int = 0) -> None:
    client.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED,
                                                  POSITION_AND_YAW_MASK | mask,
                                                  x, y, z, 0, 0, 0, 0, 0, 0, yaw, 0.0)  # fmt: skip


@pytest.mark.parametrize(("yaw_setting", "yaw_ignored"), [("command", False), ("free", True)])
def test_the_fc_link_sends_the_yaw_only_when_told_to(yaw_setting: str, yaw_ignored: bool) -> None:
    """[onboard] yaw reaches the wire: "free" sets IGNORE_YAW on every setpoint, "command" on none."""
    port = free_udp_port()
    receiver = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    link = FcLink(f"udpout:127.0.0.1:{port}", fly_yaw=yaw_setting == "command")
    try:
        link.send_accel((0.0, 0.0, 0.0), 1.0)
        link.send_position((1.0, 2.0, -1.5), 1.0)
        masks = []
        deadline = time.monotonic() + 5
        while len(masks) < 2 and time.monotonic() < deadline:
            msg = receiver.recv_match(type="SET_POSITION_TARGET_LOCAL_NED", blocking=True, timeout=1)
            if msg is not None:
                masks.append(msg.type_mask)
        assert len(masks) == 2
        assert [bool(mask & IGNORE_YAW) for mask in masks] == [yaw_ignored, yaw_ignored]
    finally:
        link.close()
        receiver.close()


def test_telemetry_rates_and_identity(vehicle: tuple[VehicleProcess, Any]) -> None:
    _, client = vehicle
    hb = client.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert client.target_system == 1
    # 50 Hz in simulated time (time_boot_ms), whatever the load on this machine does to wall time.
    stamps = []
    while len(stamps) < 50:
        msg = client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=5)
        assert msg is not None
        stamps.append(msg.time_boot_ms)
    gaps = {b - a for a, b in itertools.pairwise(stamps)}
    assert gaps == {20}
    assert wait_for(client, lambda m: True, "ATTITUDE_QUATERNION", 2) is not None
    assert wait_for(client, lambda m: True, "EXTENDED_SYS_STATE", 3).landed_state == 1  # on ground


def test_arm_takeoff_offboard_and_fly(vehicle: tuple[VehicleProcess, Any]) -> None:
    _, client = vehicle
    assert command(client, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert command(client, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mavlink.MAV_RESULT_ACCEPTED
    wait_for(client, lambda m: m.z < -1.8, "LOCAL_POSITION_NED", 15)
    # Offboard is refused before setpoints stream...
    result = command(client, mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0)
    assert result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    # ...and accepted once they do.
    for _ in range(10):
        send_setpoint(client, 0.0, 0.0, -2.0)
        client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=1)
    assert command(client, mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
    hb = wait_for(client, lambda m: m.custom_mode == 6 << 16, "HEARTBEAT", 3)
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    deadline = time.monotonic() + 20
    reached = False
    while time.monotonic() < deadline and not reached:
        send_setpoint(client, 1.0, 0.5, -2.0)
        pos = client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=1)
        reached = pos is not None and abs(pos.x - 1.0) < 0.05 and abs(pos.y - 0.5) < 0.05
    assert reached
    # The yaw of the setpoint is flown too (the onboard daemon sends the MPC's heading this way).
    deadline = time.monotonic() + 10
    yaw = 0.0
    while time.monotonic() < deadline and abs(yaw - 1.0) > 0.05:
        send_setpoint(client, 1.0, 0.5, -2.0, yaw=1.0)
        att = client.recv_match(type="ATTITUDE_QUATERNION", blocking=True, timeout=1)
        yaw = yaw_of((att.q1, att.q2, att.q3, att.q4)) if att is not None else yaw
    assert yaw == pytest.approx(1.0, abs=0.05)
    # With IGNORE_YAW the heading is the FC's own: a setpoint's yaw changes nothing.
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:
        send_setpoint(client, 1.0, 0.5, -2.0, yaw=-1.0, mask=IGNORE_YAW)
        att = client.recv_match(type="ATTITUDE_QUATERNION", blocking=True, timeout=1)
        yaw = yaw_of((att.q1, att.q2, att.q3, att.q4)) if att is not None else yaw
    assert yaw == pytest.approx(1.0, abs=0.1)
    # Setpoints stop: after COM_OF_LOSS_T the vehicle holds (AUTO.LOITER).
    wait_for(client, lambda m: m.custom_mode == (4 << 16) | (3 << 24), "HEARTBEAT", 5)


def test_message_intervals_are_honoured_as_px4_does(vehicle: tuple[VehicleProcess, Any]) -> None:
    _, client = vehicle
    position, attitude = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
    interval = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL

    def gaps(kind: str, count: int = 12) -> set[int]:
        client.recv_match(type=kind, blocking=True, timeout=5)  # the first may predate the change
        stamps = [wait_for(client, lambda m: True, kind, 5).time_boot_ms for _ in range(count)]
        return {b - a for a, b in itertools.pairwise(stamps)}

    assert command(client, interval, position, 100_000) == mavlink.MAV_RESULT_ACCEPTED  # 10 Hz
    assert gaps("LOCAL_POSITION_NED") == {100}  # in simulated time
    assert command(client, interval, attitude, -1) == mavlink.MAV_RESULT_ACCEPTED  # off
    client.recv_match(type="ATTITUDE_QUATERNION", blocking=True, timeout=0.5)
    assert client.recv_match(type="ATTITUDE_QUATERNION", blocking=True, timeout=1.5) is None
    assert command(client, interval, attitude, 0) == mavlink.MAV_RESULT_ACCEPTED  # back to the default
    assert command(client, interval, position, 0) == mavlink.MAV_RESULT_ACCEPTED
    assert gaps("ATTITUDE_QUATERNION") == {20}
    assert gaps("LOCAL_POSITION_NED") == {20}
    assert command(client, interval, mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 100_000) == mavlink.MAV_RESULT_DENIED
    assert command(client, interval, position, -5) == mavlink.MAV_RESULT_DENIED


def test_unknown_and_bad_commands_are_refused(vehicle: tuple[VehicleProcess, Any]) -> None:
    _, client = vehicle
    assert command(client, mavlink.MAV_CMD_DO_FLIGHTTERMINATION, 1) == mavlink.MAV_RESULT_UNSUPPORTED
    assert command(client, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 7) == mavlink.MAV_RESULT_DENIED
    assert command(client, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mavlink.MAV_RESULT_DENIED
    assert command(client, mavlink.MAV_CMD_DO_SET_MODE, 1, 99, 0) == mavlink.MAV_RESULT_UNSUPPORTED
    assert command(client, mavlink.MAV_CMD_DO_SET_MODE, 0, 6, 0) == mavlink.MAV_RESULT_UNSUPPORTED


def test_random_bytes_on_the_port_change_nothing(vehicle: tuple[VehicleProcess, Any]) -> None:
    proc, client = vehicle
    bind_port = proc.info["links"]["offboard"]["bind"]
    rng = __import__("random").Random(7)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for i in range(500):
            size = rng.randint(0, 300)
            payload = bytes(rng.getrandbits(8) for _ in range(size))
            if i % 5 == 0:
                payload = b"\xfd" + payload  # looks like a MAVLink 2 start
            sock.sendto(payload, ("127.0.0.1", bind_port))
    # Still alive, still disarmed, still answering on the real client's address.
    hb = wait_for(client, lambda m: True, "HEARTBEAT", 5)
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert command(client, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert proc.proc.poll() is None


def test_bad_vehicle_config_exits_2(tmp_path: Path) -> None:
    config = tmp_path / "bad.toml"
    config.write_text("[vehicle]\nspeed = 0\n")
    args = [DYNQOS, "sim", "vehicle", "--config", str(config)]
    result = subprocess.run(args, capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"dynqos: error: {config}: vehicle.speed: must be in 0.01..100 (x real time)"
    ]


MAVPROXY = shutil.which("mavproxy.py") or str(Path(sys.executable).parent / "mavproxy.py")


@pytest.mark.slow
def test_mavproxy_ground_station_sees_heartbeat_mode_and_position(tmp_path: Path) -> None:
    if not Path(MAVPROXY).exists():
        pytest.skip("mavproxy.py is not installed (.ci/run installs it with pip --no-deps mavproxy pyserial)")
    gcs_port = free_udp_port()
    api_port = free_udp_port()
    client = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{api_port}", source_system=254, source_component=190
    )
    vehicle = VehicleProcess(tmp_path, api_port, gcs_port)
    tlog = tmp_path / "gcs.tlog"
    gcs = subprocess.Popen(
        [MAVPROXY, f"--master=udpin:127.0.0.1:{gcs_port}", "--daemon", "--non-interactive",
         f"--state-basedir={tmp_path}", f"--logfile={tlog}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path,
    )  # fmt: skip
    seen: list[str] = []

    def gcs_says(text: str, timeout_s: float) -> None:
        assert gcs.stdout is not None
        deadline = time.monotonic() + timeout_s
        with selectors.DefaultSelector() as selector:
            selector.register(gcs.stdout, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if any(text in line for line in seen):
                    return
                if selector.select(timeout=max(0.0, deadline - time.monotonic())):
                    line = gcs.stdout.readline()
                    if not line:
                        break
                    seen.append(line)
        raise AssertionError(f"MAVProxy never said {text!r}; it said: {''.join(seen)[-2000:]}")

    try:
        gcs_says("Detected vehicle 1:1", 30)
        assert client.wait_heartbeat(timeout=10) is not None
        assert command(client, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        gcs_says("ARMED", 10)
        assert (
            command(client, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mavlink.MAV_RESULT_ACCEPTED
        )
        wait_for(client, lambda m: m.z < -1.8, "LOCAL_POSITION_NED", 15)
        for _ in range(10):
            send_setpoint(client, 0.0, 0.0, -2.0)
            client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=1)
        assert command(client, mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
        for _ in range(25):
            send_setpoint(client, 0.0, 0.0, -2.0)
            client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=1)
        gcs_says("OFFBOARD", 10)
    finally:
        gcs.terminate()  # our own child, by its pid
        try:
            gcs.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            gcs.kill()
            gcs.communicate(timeout=5)
        client.close()
        vehicle.stop()
    log = mavutil.mavlink_connection(str(tlog))
    altitudes = []
    while (msg := log.recv_match(type="LOCAL_POSITION_NED")) is not None:
        altitudes.append(-msg.z)
    assert altitudes, "the ground station logged no position"
    assert max(altitudes) > 1.8


def _lockstep_flight(
    tmp_path: Path, seconds: float, extra_args: tuple[str, ...] = ()
) -> tuple[list[tuple[int, float, float, float]], float, str]:
    """Fly a scripted mission against `--lockstep`: one setpoint per telemetry period, commands at
    fixed periods. Returns the LOCAL_POSITION_NED trace, the wall time and the vehicle's stderr."""
    port = free_udp_port()
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    config = tmp_path / "vehicle.toml"
    config.write_text(
        f"[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\noffboard_remote_port = {port}\n"
        f"gcs_remote_port = {free_udp_port()}\ngust_std_mps = 0.5\nseed = 7\n"
    )
    proc = DynqosProcess(["sim", "vehicle", "--lockstep", "--duration", str(seconds), *extra_args], config)
    trace: list[tuple[int, float, float, float]] = []
    try:
        assert proc.info["clock"] == "lockstep"
        wall_start = time.monotonic()
        while len(trace) < seconds * 50:
            pos = client.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=5)
            assert pos is not None, "lock-step vehicle stopped sending telemetry"
            if trace and pos.time_boot_ms == trace[-1][0]:
                continue  # the repeated telemetry of a silent period, not a new one
            trace.append((pos.time_boot_ms, pos.x, pos.y, pos.z))
            tick = len(trace)
            script = {  # period -> command and its params
                5: (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, 0),
                6: (mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 2.0),
                250: (mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0),
            }
            if tick in script:
                cmd, p1, p2, p7 = script[tick]
                client.mav.command_long_send(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, p7)
            send_setpoint(client, 1.0, 0.5, -2.0)  # closes the period: the vehicle advances 20 ms
        wall_s = time.monotonic() - wall_start
    finally:
        client.close()
        err = proc.stop()
    return trace, wall_s, err


def test_lockstep_is_deterministic_and_faster_than_real_time(tmp_path: Path) -> None:
    seconds = 8.0
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first, wall_s, _ = _lockstep_flight(tmp_path / "a", seconds)
    second, _, _ = _lockstep_flight(tmp_path / "b", seconds)
    # Every period is 20 ms of simulated time, whatever the wall clock did.
    assert [t for t, *_ in first] == list(range(0, int(seconds * 1000), 20))
    assert first == second  # same seed, same messages: the same flight, gusts included
    _, x, y, z = first[-1]
    assert (x, y, z) == pytest.approx((1.0, 0.5, -2.0), abs=0.1)  # took off, flew offboard
    assert wall_s < seconds  # faster than real time (the peer is the only pace)


def test_contacts_with_the_world_are_logged_and_counted(tmp_path: Path) -> None:
    world = tmp_path / "pillar.toml"
    world.write_text("[[cylinders]]\ncenter_m = [1.0, 0.5]\nradius_m = 0.2\nz_top_m = -3.0\n")
    _, _, err = _lockstep_flight(tmp_path, 8.0, ("--world", str(world)))
    assert "collision with cylinder 0" in err
    assert "'collisions': 1" in err  # the exit summary counts one contact, not one per period


def test_bad_world_file_exits_2(tmp_path: Path) -> None:
    world = tmp_path / "bad.toml"
    world.write_text("[[cylinders]]\ncenter_m = [1.0, 0.5]\nradius_m = -1\n")
    for path in (world, tmp_path / "missing.toml"):
        proc = subprocess.run(
            [DYNQOS, "sim", "vehicle", "--world", str(path)], capture_output=True, text=True, timeout=30
        )
        assert proc.returncode == 2
        assert proc.stderr.count("\n") == 1
        assert str(path) in proc.stderr


def test_instances_follow_px4_sitl_ids_and_ports_and_one_ground_station_sees_them_all(tmp_path: Path) -> None:
    """`--instance N`: system id N+1, offboard to 14540+N's stand-in (base + N), every vehicle to one GCS
    port; a command for one system moves only that vehicle; each stands where [vehicle] start_m says."""
    base, gcs_port = free_udp_port(), free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=255, source_component=190)
    offboard = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{base + 2}", source_system=255, source_component=1
    )
    config = tmp_path / "vehicle.toml"
    config.write_text(
        f"[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\noffboard_remote_port = {base}\n"
        f"gcs_remote_port = {gcs_port}\nstart_m = [3.0, -4.0]\n"
    )
    procs = [
        DynqosProcess(["sim", "vehicle", "--instance", str(n), "--duration", "120"], config) for n in (1, 2)
    ]
    try:
        assert offboard.wait_heartbeat(timeout=10) is not None
        assert offboard.target_system == 3  # instance 2 on its own offboard port
        pos = wait_for(offboard, lambda m: True, "LOCAL_POSITION_NED", 5)
        assert (pos.x, pos.y) == pytest.approx((3.0, -4.0), abs=0.01)
        seen: set[int] = set()
        deadline = time.monotonic() + 10
        while seen != {2, 3} and time.monotonic() < deadline:
            hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
            if hb is not None:
                seen.add(hb.get_srcSystem())
        assert seen == {2, 3}

        offboard.mav.command_long_send(3, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = wait_for(
            offboard, lambda m: m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM, "COMMAND_ACK", 10
        )
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        armed: dict[int, bool] = {}
        deadline = time.monotonic() + 10
        while not armed.get(3) or 2 not in armed:
            assert time.monotonic() < deadline, armed
            hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
            if hb is not None:
                armed[hb.get_srcSystem()] = bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        assert armed == {2: False, 3: True}
    finally:
        for proc in procs:
            proc.stop()
        gcs.close()
        offboard.close()


def test_a_bad_instance_exits_2(tmp_path: Path) -> None:
    config = tmp_path / "vehicle.toml"
    config.write_text("[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\n")
    result = subprocess.run(
        [DYNQOS, "sim", "vehicle", "--instance", "300", "--config", str(config)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert "--instance must be in 0..254" in result.stderr
    assert "Traceback" not in result.stderr
