"""The flight-controller link over a serial line, as a companion computer meets a Pixhawk: the simulator
on one side of a pseudo-terminal pair, the onboard link (pyserial, through pymavlink) on the other; the
loop flown over it; the device vanishing mid-flight is an FC silence, not a crash (docs/onboard.md)."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from dynqos.onboard.fclink import FcLink
from dynqos.sim.vehicle.serial_link import SerialLink
from tests.procs import DynqosProcess
from tests.test_onboard_loop import Observer, edge_loop
from tests.test_vehicle_mavlink import free_udp_port

pytestmark = [pytest.mark.integration]
PTY = {"DYNQOS_VEHICLE__OFFBOARD_SERIAL": "pty"}


def _serial_vehicle(tmp_path: Path) -> DynqosProcess:
    config = tmp_path / "vehicle.toml"
    config.write_text(
        f'[vehicle]\noffboard_serial = "pty"\ngcs_bind_port = 0\ngcs_remote_port = {free_udp_port()}\n'
    )
    return DynqosProcess(["sim", "vehicle", "--duration", "120"], config)


def test_a_bad_baud_rate_is_refused() -> None:
    with pytest.raises(ValueError, match="baud 12345"):
        SerialLink("offboard", "pty", baud=12345)


@pytest.mark.timeout(120)
def test_the_onboard_link_reads_telemetry_and_commands_the_vehicle_over_a_pty(tmp_path: Path) -> None:
    """The ready line names the pty; the onboard link opens it as it would /dev/ttyACM0 (device,baud),
    gets telemetry, arms, and sees the vehicle go silent, without an exception, when it exits."""
    vehicle = _serial_vehicle(tmp_path)
    link = None
    try:
        device = vehicle.info["links"]["offboard"]["serial"]
        assert device.startswith("/dev/pts/")
        link = FcLink(f"{device},921600", heartbeat_timeout_s=1.0)
        link.start()
        assert link.wait_ready(10.0)  # its heartbeat and a position came over the line
        assert link.arm() == mavlink.MAV_RESULT_ACCEPTED  # a command and its ack, both ways
        vehicle.proc.send_signal(signal.SIGKILL)  # the device goes away with its process
        vehicle.proc.wait(timeout=10)
        deadline = time.monotonic() + 10
        while not link.heartbeat_lost() and time.monotonic() < deadline:
            time.sleep(0.05)  # the silence is a matter of time (heartbeat_timeout_s): nothing to await
        assert link.heartbeat_lost()
        assert link._thread is not None
        assert link._thread.is_alive()  # the reader survived the device's end
    finally:
        if link is not None:
            link.close()
        vehicle.stop()


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_loop_closes_over_a_serial_link_and_survives_its_loss(tmp_path: Path) -> None:
    """The demo drone flown with its FC on a pty: it takes off, the edge flies the circle within 0.5 m
    after the lead-in, the vehicle receives setpoints at the daemon's 50 Hz; then the vehicle and its
    device vanish: the daemon logs the FC's silence and keeps running."""
    with edge_loop(tmp_path, vehicle_env=PTY) as (config, zcfg, procs):
        device = procs["vehicle"].info["links"]["offboard"]["serial"]
        observer = Observer(zcfg)
        try:
            procs["onboard"] = DynqosProcess(
                ["onboard", "--takeoff"], config, env={"DYNQOS_ONBOARD__MAVLINK_URL": f"{device},921600"}
            )
            assert observer.wait_until(lambda s: s.mode == "offboard", 60), "the drone never offloaded"
            offboard_at = time.monotonic()
            observer.wait_until(lambda s: False, 4.0)  # the 3 s lead-in onto the circle
            start = time.monotonic_ns()
            observer.wait_until(lambda s: False, 5.0)
            errors = observer.tracking_errors(start)
        finally:
            observer.bus.close()
        flown_s = time.monotonic() - offboard_at
        vehicle = procs.pop("vehicle").stop()
        onboard = procs["onboard"]
        deadline = time.monotonic() + 20
        noticed = False
        for line in onboard.lines(5.0):  # its log as it comes
            noticed = "no heartbeat from the flight controller" in line
            if noticed or time.monotonic() > deadline:
                break
        assert noticed, "the daemon did not notice the FC's silence"
        assert onboard.alive()
        log = procs.pop("onboard").stop()
    assert len(errors) > 50
    assert max(errors) < 0.5
    setpoints = int(vehicle.split("'setpoints': ")[1].split(",")[0])
    assert setpoints >= 45 * flown_s, (setpoints, flown_s)  # 50 Hz, a few ticks of slack
    assert "Traceback" not in log
    assert "fc link: cannot read" in log
