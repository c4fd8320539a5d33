"""The onboard daemon's pure parts: command validation and timing, camera latency, fallback PID, camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dynqos.common.depthcodec import decode_zstd16
from dynqos.common.messages import CameraAck, Command
from dynqos.onboard.camera import FilesCamera, RateController, encode_depth, encode_rgb
from dynqos.onboard.commands import CommandTracker
from dynqos.onboard.monitors import CameraLatencyMonitor
from dynqos.onboard.pid import CascadedPid
from dynqos.onboard.risk import Spaciousness
from dynqos.sim.vehicle.model import VehicleModel
from dynqos.sim.vehicle.px4 import MAIN_OFFBOARD, Setpoint

MS = 1_000_000


def command(state_seq: int, stamp: int, *, uav: str = "uav1", hold: int = 0, k: int = 10) -> Command:
    return Command(
        uav=uav,
        seq=state_seq,
        state_seq=state_seq,
        state_stamp_ns=stamp,
        edge_hold_ns=hold,
        dt_s=0.05,
        accel_mps2=[(float(i), 0.0, 0.0) for i in range(k)],
        yaw_rad=[0.1 * i for i in range(k)],
    )


def test_commands_are_validated_timed_and_give_the_rtt() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    assert tracker.watchdog_expired(0)
    tracker.state_sent(1, 1000 * MS)
    tracker.state_sent(2, 1050 * MS)
    assert tracker.oldest_unanswered_ms(1060 * MS) == pytest.approx(60.0)
    assert tracker.offer(command(1, 1000 * MS, hold=2 * MS), 1030 * MS)
    assert tracker.last_rtt_ms == pytest.approx(28.0)  # arrival - stamp - edge hold
    assert tracker.setpoint(1030 * MS).accel_mps2 == (0.0, 0.0, 0.0)
    sp = tracker.setpoint(1120 * MS)
    assert (sp.index, sp.accel_mps2[0], sp.yaw_rad) == (2, 2.0, pytest.approx(0.2))
    assert tracker.oldest_unanswered_ms(1060 * MS) == pytest.approx(10.0)
    assert not tracker.watchdog_expired(1170 * MS)
    assert tracker.watchdog_expired(1181 * MS)  # 150 ms after the last valid command
    # duplicates, replays, reordering, other drones, unknown states, future and expired horizons
    assert not tracker.offer(command(1, 1000 * MS), 1040 * MS)  # a duplicate: state 1 is answered
    assert not tracker.offer(command(2, 1050 * MS, uav="uav2"), 1060 * MS)
    assert not tracker.offer(command(3, 1100 * MS), 1110 * MS)  # we never sent state 3
    assert not tracker.offer(command(2, 1051 * MS), 1060 * MS)  # the stamp was altered
    tracker.state_sent(4, 2000 * MS)
    assert not tracker.offer(command(4, 2000 * MS), 1990 * MS)  # from the future
    tracker.state_sent(5, 3000 * MS)
    assert not tracker.offer(command(5, 3000 * MS, k=2), 3200 * MS)  # horizon over on arrival
    c = tracker.counters
    counts = (c.accepted, c.duplicates, c.wrong_drone, c.unknown_state, c.future, c.expired)
    assert counts == (1, 1, 1, 2, 1, 1)
    assert c.rejected == 5  # a duplicate is dropped and counted apart: two paths make them all the time
    assert tracker.take_new_rtts() == [pytest.approx(28.0)]
    assert tracker.take_new_rtts() == []
    assert tracker.setpoint(0) is None
    assert tracker.setpoint(1000 * MS + 10 * 50 * MS) is None  # past the horizon: no setpoint, watchdog


def test_unanswered_states_are_bounded() -> None:
    tracker = CommandTracker("uav1", watchdog_ns=150 * MS)
    for seq in range(1000):
        tracker.state_sent(seq, seq * MS)
    assert tracker.oldest_unanswered_ms(1000 * MS) == pytest.approx(256.0)


def test_camera_latency_from_acks() -> None:
    monitor = CameraLatencyMonitor(max_outstanding=4)
    for seq in range(1, 4):
        monitor.frame_sent(seq, "rgb", seq * 100 * MS)
    assert monitor.oldest_outstanding_ms(350 * MS) == pytest.approx(250.0)
    ack = CameraAck(uav="u", seq=2, frame_seq=2, kind="rgb", stamp_ns=200 * MS, edge_hold_ns=5 * MS)
    assert monitor.on_ack(ack, 260 * MS) == pytest.approx(55.0)
    assert monitor.oldest_outstanding_ms(350 * MS) == pytest.approx(50.0)  # frame 1 is given up
    assert monitor.on_ack(ack, 270 * MS) is None  # a duplicate ack
    assert monitor.take_new() == [pytest.approx(55.0)]
    for seq in range(10, 20):
        monitor.frame_sent(seq, "rgb", seq * MS)
    assert monitor.oldest_outstanding_ms(20 * MS) == pytest.approx(4.0)  # bounded to 4 outstanding


def test_fallback_pid_holds_brakes_and_does_not_wind_up() -> None:
    model = VehicleModel()
    fc = model.fc
    fc.arm(True, model.state, True, 0)
    fc.takeoff(1.5, model.state, 0)
    model.advance(6.0)
    for _ in range(5):
        fc.on_setpoint(Setpoint(vel_mps=(0.0, 0.0, 0.0)), model.now_ns)
        model.advance(0.02)
    fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns)
    for _ in range(150):  # flying at 1.26 m/s, like the demo's circle
        fc.on_setpoint(Setpoint(vel_mps=(1.26, 0.0, 0.0), yaw_rad=0.0), model.now_ns)
        model.advance(0.02)
    pid = CascadedPid()
    pid.reset(np.zeros(3))
    hold = model.state.pos_m.copy()
    distances = []
    for _ in range(300):
        accel = pid.step(model.state.pos_m, model.state.vel_mps, hold, 0.02)
        assert np.all(np.abs(accel) <= np.array(pid.gains.accel_max_mps2) + 1e-12)
        fc.on_setpoint(Setpoint(accel_mps2=tuple(accel), yaw_rad=0.0), model.now_ns)
        model.advance(0.02)
        distances.append(float(np.linalg.norm(model.state.pos_m - hold)))
    assert max(distances) < 0.35
    assert distances[-1] < 0.05


def test_pid_is_bumpless_and_bounded() -> None:
    pid = CascadedPid()
    pid.reset(np.array([1.0, -0.5, 0.2]))
    first = pid.step(np.zeros(3), np.zeros(3), np.zeros(3), 0.02)
    assert first == pytest.approx([1.0, -0.5, 0.2])  # at zero error it continues the last command
    for _ in range(1000):  # a target it cannot reach quickly: saturated, the integrator must not run away
        pid.step(np.zeros(3), np.zeros(3), np.array([100.0, 0.0, 0.0]), 0.02)
    recovered = pid.step(np.zeros(3), np.zeros(3), np.zeros(3), 0.02)
    assert abs(recovered[0]) < 3.0


def test_rate_controller() -> None:
    rate = RateController(10.0)
    grabs = [t for t in range(0, 1000 * MS, MS) if rate.due(t)]
    assert len(grabs) == pytest.approx(10, abs=1)
    rate.factor = 0.5
    grabs = [t for t in range(1000 * MS, 3000 * MS, MS) if rate.due(t)]
    assert len(grabs) == pytest.approx(10, abs=1)
    rate.factor = 0.0
    assert not rate.due(10_000 * MS)


def test_files_camera_streams_real_frames(shared_data: Path) -> None:
    camera = FilesCamera(shared_data / "rgbd", (518.0, 519.0, 325.5, 253.5))
    assert len(camera.frames) == 5
    risk = Spaciousness(640, 480, (518.0, 519.0, 325.5, 253.5))
    values = []
    for _ in range(5):
        frame = camera.grab(None)
        assert frame is not None
        assert frame.rgb.shape == (480, 640, 3)
        assert frame.depth_m is not None
        jpeg, depth = encode_rgb(frame.rgb, 90), encode_depth(frame.depth_m)
        decoded = decode_zstd16(depth, 640, 480)
        assert np.array_equal(decoded, np.round(frame.depth_m * 1000).astype(np.uint16))  # lossless
        assert 20_000 < len(jpeg) < 200_000
        values.append(risk(frame.depth_m))
    print("spaciousness of the real frames (m):", [round(v or 0, 2) for v in values])
    assert all(v is not None and 1.0 <= v <= 10.0 for v in values)


def test_depth_is_counted_as_before_and_travels_losslessly() -> None:
    """encode_depth's counts in one buffer equal the plain formula (half to even, clipped to 16 bits),
    and zstd16 gives them back exactly, odd sizes included."""
    rng = np.random.default_rng(7)
    for shape in ((480, 640), (3, 5), (1, 1)):
        depth = rng.uniform(-1.0, 70.0, shape).astype(np.float32)
        depth.flat[0] = 0.0005  # a tie: rounds to 0, as np.round does
        expected = np.clip(np.round(depth / 0.001), 0, 65535).astype(np.uint16)
        assert np.array_equal(decode_zstd16(encode_depth(depth), shape[1], shape[0]), expected)


def test_serial_urls_carry_their_baud_rate() -> None:
    from dynqos.onboard.fclink import serial_device_and_baud

    assert serial_device_and_baud("/dev/ttyACM0,57600") == ("/dev/ttyACM0", 57600)
    assert serial_device_and_baud("/dev/ttyTHS1") == ("/dev/ttyTHS1", 921600)
    assert serial_device_and_baud("udpin:127.0.0.1:14540") == ("udpin:127.0.0.1:14540", 921600)
    assert serial_device_and_baud("tcp:host:5760,1") == ("tcp:host:5760,1", 921600)  # not a serial URL


def test_nan_and_infinite_setpoints_are_refused_by_the_decoder() -> None:
    import math

    import msgpack

    from dynqos.common.errors import DecodeError
    from dynqos.common.messages import decode, encode

    body = msgpack.unpackb(encode(command(1, 1000 * MS)), raw=False)
    for bad in (math.nan, math.inf, -math.inf):
        body["accel_mps2"] = [[bad, 0.0, 0.0]]
        with pytest.raises(DecodeError, match=r"accel_mps2\[0\]"):
            decode(msgpack.packb(body, use_bin_type=True))


def test_the_daemon_ticks_at_the_configured_setpoint_rate() -> None:
    from dynqos.common.config import Config, ControlConfig
    from dynqos.onboard.core import SETPOINT_PERIOD_NS, setpoint_period_ns

    assert setpoint_period_ns(Config()) == SETPOINT_PERIOD_NS == 20_000_000
    assert setpoint_period_ns(Config(control=ControlConfig(setpoint_hz=25.0))) == 40_000_000
