"""MAVLink 2 signing on the flight-controller link: the key file, the simulator refusing what PX4 refuses
once a key is provisioned (unsigned, a wrong key, a replay), the onboard link signing and checking, and
the whole loop flown signed (docs/onboard.md, "Signing")."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common import mavsign
from dynqos.common.errors import ConfigError, DynqosError
from dynqos.onboard.fclink import FcLink, use_mavlink2
from dynqos.reports.outcomes import log_times
from tests.procs import DYNQOS, DynqosProcess
from tests.test_onboard_loop import Observer, edge_loop
from tests.test_vehicle_mavlink import free_udp_port

ARM, TAKEOFF = mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF
REQUEST, INTERVAL = mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL


def test_the_key_file_is_32_bytes_owner_only_and_never_shown(tmp_path: Path) -> None:
    path = mavsign.write_key(tmp_path / "keys" / "fc.key")
    assert os.stat(path).st_mode & 0o777 == 0o600
    key = mavsign.load_key(path)
    assert len(key) == 32
    assert path.read_text().strip() == key.hex()
    with pytest.raises(DynqosError, match="exists"):
        mavsign.write_key(path)
    assert mavsign.load_key(mavsign.write_key(path, force=True)) != key
    raw = tmp_path / "raw.key"
    raw.write_bytes(bytes(range(32)))
    raw.chmod(0o600)
    assert mavsign.load_key(raw) == bytes(range(32))
    raw.chmod(0o640)
    with pytest.raises(ConfigError, match="chmod 600"):
        mavsign.load_key(raw)
    short = tmp_path / "short.key"
    short.write_text("ab" * 31)
    short.chmod(0o600)
    with pytest.raises(ConfigError, match="64 hexadecimal") as refused:
        mavsign.load_key(short)
    assert "ab" * 31 not in str(refused.value)  # the bytes are never echoed
    with pytest.raises(ConfigError, match="cannot read"):
        mavsign.load_key(tmp_path / "absent.key")


def test_the_signing_key_command_writes_a_key_and_refuses_to_overwrite(tmp_path: Path) -> None:
    def run_dynqos(args: list[str]) -> subprocess.CompletedProcess[str]:
        return subprocess.run([DYNQOS, *args], capture_output=True, text=True, timeout=30)

    out = tmp_path / "fc.key"
    first = run_dynqos(["signing-key", "--out", str(out)])
    assert first.returncode == 0, first.stderr
    key = out.read_text()
    assert key.strip() not in first.stdout + first.stderr
    again = run_dynqos(["signing-key", "--out", str(out)])
    assert again.returncode == 2
    assert "exists" in again.stderr
    assert "Traceback" not in again.stderr
    assert out.read_text() == key


def _signer(key: bytes, link_id: int) -> Any:
    """A MAVLink sender of its own (a GCS, an attacker) signing with `key`."""
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.timestamp = mavsign.timestamp_now()
    mav.signing.sign_outgoing = True
    return mav


def _arm_packet(mav: Any, command: int, *params: float) -> bytes:
    p = [*params, 0, 0, 0, 0, 0, 0, 0][:7]
    return bytes(mav.command_long_encode(1, 1, command, 0, *p).pack(mav))


def _vehicle(tmp_path: Path, key_file: Path | None, remote: int, bind: int) -> DynqosProcess:
    config = tmp_path / "vehicle.toml"
    config.write_text(
        f"[vehicle]\noffboard_bind_port = {bind}\ngcs_bind_port = 0\noffboard_remote_port = {remote}\n"
        f"gcs_remote_port = {free_udp_port()}\n" + (f'signing_key = "{key_file}"\n' if key_file else "")
    )
    return DynqosProcess(["sim", "vehicle", "--duration", "120"], config)


def _acks_until(client: Any, command: int) -> list[int]:
    """Every COMMAND_ACK's command up to and including the one for `command`."""
    seen: list[int] = []
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        ack = client.recv_match(type="COMMAND_ACK", blocking=True, timeout=1)
        if ack is not None:
            seen.append(ack.command)
            if ack.command == command:
                return seen
    raise AssertionError(f"no COMMAND_ACK for {command}; saw {seen}")


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_a_signing_vehicle_refuses_unsigned_wrongly_signed_and_replayed_commands(tmp_path: Path) -> None:
    """As PX4 with a key provisioned: its messages are signed; a command unsigned, signed with another
    key, or replayed byte for byte is refused and counted; an unsigned HEARTBEAT passes; a correctly
    signed one is obeyed. The datagrams go in order over one socket, so the signed command sent last
    is answered after every earlier one has been judged."""
    key_file = mavsign.write_key(tmp_path / "fc.key")
    key = mavsign.load_key(key_file)
    remote, bind = free_udp_port(), free_udp_port()
    use_mavlink2()  # a signing client must not start on MAVLink 1 (onboard/fclink.py)
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{remote}", source_system=255, source_component=190)
    client.setup_signing(key, sign_outgoing=True, link_id=1, initial_timestamp=mavsign.timestamp_now())
    vehicle = _vehicle(tmp_path, key_file, remote, bind)
    try:
        assert client.wait_heartbeat(timeout=10) is not None
        assert client.mav.signing.goodsig_count > 0  # the vehicle signs what it sends
        to_vehicle = ("127.0.0.1", bind)
        unsigned = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        client.port.sendto(_arm_packet(unsigned, ARM, 1), to_vehicle)
        client.port.sendto(bytes(unsigned.heartbeat_encode(6, 8, 0, 0, 4).pack(unsigned)), to_vehicle)
        client.port.sendto(_arm_packet(_signer(os.urandom(32), 2), TAKEOFF, 0, 0, 0, 0, 0, 0, 2), to_vehicle)
        request = _arm_packet(_signer(key, 3), REQUEST, 0)  # correctly signed: obeyed once
        client.port.sendto(request, to_vehicle)
        client.port.sendto(request, to_vehicle)  # the same bytes again: a replay
        client.mav.command_long_send(
            1, 1, INTERVAL, 0, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0, 0, 0, 0, 0, 0
        )
        assert _acks_until(client, INTERVAL) == [REQUEST, INTERVAL]  # no ARM, no TAKEOFF, one REQUEST
    finally:
        client.close()
        log = vehicle.stop()
    stopped = re.search(r"vehicle stopped: (\{.*\})", log)
    assert stopped, log[-2000:]
    counters = ast.literal_eval(stopped.group(1))  # the vehicle logs its counters as a dict
    assert counters["unsigned_refused"] == 1
    assert counters["bad_signature"] == 2  # the wrong key and the replay
    assert "signing is on: refused an unsigned message" in log
    assert key.hex() not in log


@pytest.mark.integration
@pytest.mark.timeout(120)
def test_a_vehicle_without_a_key_accepts_signed_and_unsigned_alike(tmp_path: Path) -> None:
    """Signing off (PX4 with no key): a signing peer is obeyed as before, and nothing sent is signed."""
    remote, bind = free_udp_port(), free_udp_port()
    use_mavlink2()
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{remote}", source_system=255, source_component=190)
    client.setup_signing(os.urandom(32), link_id=1, allow_unsigned_callback=lambda *_: True)  # accepts all
    vehicle = _vehicle(tmp_path, None, remote, bind)
    try:
        assert client.wait_heartbeat(timeout=10) is not None
        assert client.mav.signing.goodsig_count == 0
        client.port.sendto(_arm_packet(mavlink.MAVLink(None, srcSystem=255, srcComponent=190), REQUEST, 0),
                           ("127.0.0.1", bind))  # fmt: skip
        client.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert _acks_until(client, ARM) == [REQUEST, ARM]
    finally:
        client.close()
        log = vehicle.stop()
    assert "'unsigned_refused': 0, 'bad_signature': 0" in log


@pytest.mark.integration
@pytest.mark.timeout(120)
@pytest.mark.parametrize("same_key", [True, False])
def test_the_onboard_link_signs_and_refuses_a_vehicle_with_another_key(
    tmp_path: Path, same_key: bool
) -> None:
    """FcLink with a key: against a vehicle with the same key it is ready and arms; against one with
    another key it hears nothing it accepts (counted) and the vehicle obeys none of its commands."""
    key_file = mavsign.write_key(tmp_path / "fc.key")
    other = mavsign.write_key(tmp_path / "other.key")
    remote, bind = free_udp_port(), free_udp_port()
    vehicle = _vehicle(tmp_path, key_file if same_key else other, remote, bind)
    link = FcLink(f"udpin:127.0.0.1:{remote}", signing_key=mavsign.load_key(key_file), link_id=1)
    try:
        link.start()
        ready = link.wait_ready(5.0 if same_key else 2.0)
        counts = link.signing_counts()
        if same_key:
            assert ready
            assert counts["signed_ok"] > 0
            assert counts["refused"] == 0
            assert link.arm() == mavlink.MAV_RESULT_ACCEPTED
        else:
            assert not ready
            assert counts["refused"] > 0
            assert counts["signed_ok"] == 0
    finally:
        link.close()
        log = vehicle.stop()
    if not same_key:
        assert "signing is on: refused a badly signed or replayed message" in log


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("signed", [True, False], ids=["signed", "unsigned"])
def test_the_loop_closes_with_the_flight_controller_link_signed_or_not(tmp_path: Path, signed: bool) -> None:
    """The demo drone with signing on both ends of its MAVLink link, and with it off on both: it takes
    off, is flown by the edge, tracks its circle, and no message either way is refused."""
    key_file = str(mavsign.write_key(tmp_path / "fc.key"))
    vehicle_env = {"DYNQOS_VEHICLE__SIGNING_KEY": key_file} if signed else None
    onboard_env = {"DYNQOS_ONBOARD__MAVLINK_SIGNING_KEY": key_file} if signed else None
    with edge_loop(tmp_path, vehicle_env=vehicle_env) as (config, zcfg, procs):
        observer = Observer(zcfg)
        try:
            procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], config, env=onboard_env)
            assert observer.wait_until(lambda s: s.mode == "offboard", 60), "the drone never offloaded"
            observer.wait_until(lambda s: False, 4.0)  # the 3 s lead-in onto the circle
            start, start_wall = time.monotonic_ns(), time.time()
            observer.wait_until(lambda s: False, 5.0)
            errors = observer.tracking_errors(start)
        finally:
            observer.bus.close()
        onboard = procs.pop("onboard").stop()
        vehicle = procs.pop("vehicle").stop()
    assert len(errors) > 50
    assert max(errors) < 0.5
    health = re.findall(r"fc_signed_ok=(\d+) fc_refused=(\d+)", onboard)
    if signed:
        assert health, onboard[-2000:]
        signed_ok, refused = (int(v) for v in health[-1])
        assert signed_ok > 1000  # 50 Hz telemetry, all of it signed and checked
        assert refused == 0
    else:
        assert health == []
    assert "'unsigned_refused': 0, 'bad_signature': 0" in vehicle
    setpoints = int(re.search(r"'setpoints': (\d+)", vehicle).group(1))  # type: ignore[union-attr]
    assert setpoints > 250
    # Flown by the edge throughout the measured span. (Until the first command reaches the offloading
    # drone, signed or not, the fallback PID may hold it for a tick or two: not measured here.)
    late = [m for t, m in log_times(onboard) if t >= start_wall and "fallback PID" in m]
    assert late == []
