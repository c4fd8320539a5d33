"""A camera's frame stamps on the daemon's clock (onboard/frame_time.py), with the clocks in the test's
hands. Through real librealsense: tests/test_realsense.py."""

from __future__ import annotations

from dynqos.onboard.frame_time import MAX_AGE_NS, DeviceTime

MS = 1_000_000
WALL = 1_795_000_000_000 * MS  # the host's wall clock when the frame is grabbed


def test_a_host_time_stamp_gives_the_frames_age() -> None:
    device = DeviceTime()
    for domain in ("global_time", "system_time"):
        captured = device.captured_ns((WALL - 35 * MS) / 1e6, domain, arrival_ns=500 * MS, wall_ns=WALL)
        assert abs(captured - 465 * MS) < 1000  # a float of epoch milliseconds: to the microsecond


def test_a_host_stamp_in_the_future_or_too_old_is_not_believed_as_an_age() -> None:
    future = DeviceTime().captured_ns((WALL + 5 * MS) / 1e6, "global_time", 500 * MS, WALL)
    old = DeviceTime().captured_ns((WALL - MAX_AGE_NS - MS) / 1e6, "global_time", 500 * MS, WALL)
    assert future == old == 500 * MS  # first frame of its window: taken as quick


def test_a_device_clock_is_mapped_by_the_quickest_frame_of_the_window() -> None:
    device = DeviceTime(window=4)
    # device clock at 0 when ours is at 1000 ms; the frames take 3, 1, 9 (a wait in the driver), 2 ms
    got = [device.captured_ns(t, "hardware_clock", (1000 + t + d) * MS, WALL)
           for t, d in ((0, 3), (66, 1), (133, 9), (200, 2))]  # fmt: skip
    assert got == [1003 * MS, 1067 * MS, 1134 * MS, 1201 * MS]  # the 9 ms frame is 8 ms older than it came
    # the quick frame leaves the window after 4 more frames: the next quickest (2 ms) counts then
    for t in (266, 333, 400):
        device.captured_ns(t, "hardware_clock", (1000 + t + 5) * MS, WALL)
    assert device.captured_ns(466, "hardware_clock", (1000 + 466 + 5) * MS, WALL) == (1000 + 466 + 5) * MS


def test_a_device_clock_that_goes_back_starts_a_new_window_and_a_repeated_frame_is_left_out() -> None:
    device = DeviceTime()
    device.captured_ns(1000, "hardware_clock", 5000 * MS, WALL)
    assert device.captured_ns(1000, "hardware_clock", 5066 * MS, WALL) == 5000 * MS  # given again, late
    assert device.captured_ns(1066, "hardware_clock", 5068 * MS, WALL) == 5066 * MS
    # the device restarted: its clock from 0 again; the old offset (4000 ms) means nothing now
    assert device.captured_ns(10, "hardware_clock", 5100 * MS, WALL) == 5100 * MS
