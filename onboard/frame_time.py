"""A camera's own frame timestamps on the daemon's clock, so that the camera latency the supervisor
measures (frame stamp to the detector's ack) starts when the camera captured the frame, not when the
daemon got it: the time a frame waits in the driver and the USB transfer count as the network's do.

A device stamps frames in one of two kinds of time (librealsense's `timestamp_domain`):
- the host's wall clock (`system_time`, and `global_time`, the device clock mapped to the host's by
  librealsense): the frame's age is the wall clock now minus its stamp, believed when it is between
  0 and MAX_AGE_NS (a stamp in the future, or older than any frame a camera holds, is a clock that
  jumped);
- anything else (`hardware_clock`, a recording's stamps): the offset to our clock is unknown. The
  smallest (arrival - stamp) over the last WINDOW frames is taken as the offset, so a frame's captured
  time is its stamp plus that offset: what is measured is how much longer a frame took than the
  quickest of the window, not the quickest one's own transfer. A stamp that goes back (a device reset,
  a recording that starts again) restarts the window; a frame given again (the same stamp, as
  librealsense's syncer does to pair it with the next depth image) is left out of it.
Pure: the caller hands in both clocks' readings.
"""

from __future__ import annotations

from collections import deque

MAX_AGE_NS = 1_000_000_000
WINDOW = 256  # frames: about 17 s at 15 fps, short against a device clock's drift
HOST_DOMAINS = frozenset({"system_time", "global_time"})


class DeviceTime:
    def __init__(self, window: int = WINDOW) -> None:
        self.window = window
        self._offsets: deque[tuple[int, int]] = deque()  # (frame index, offset), offsets increasing
        self._index = 0
        self._last_stamp_ns: int | None = None

    def captured_ns(self, stamp_ms: float, domain: str, arrival_ns: int, wall_ns: int) -> int:
        """When the frame stamped `stamp_ms` (in `domain`) was captured, on the clock of `arrival_ns`;
        `wall_ns`: the host's wall clock read together with `arrival_ns`."""
        stamp_ns = round(stamp_ms * 1e6)
        if domain in HOST_DOMAINS:
            age_ns = wall_ns - stamp_ns
            if 0 <= age_ns <= MAX_AGE_NS:
                return arrival_ns - age_ns
        if self._last_stamp_ns is not None and stamp_ns < self._last_stamp_ns:
            self._offsets.clear()
        if stamp_ns != self._last_stamp_ns:  # a frame given again says nothing of the offset
            self._push(arrival_ns - stamp_ns)
        self._last_stamp_ns = stamp_ns
        return stamp_ns + self._offsets[0][1]

    def _push(self, offset: int) -> None:
        """A sliding-window minimum: entries that can never be the minimum again are dropped."""
        while self._offsets and self._offsets[-1][1] >= offset:
            self._offsets.pop()
        self._offsets.append((self._index, offset))
        while self._offsets[0][0] <= self._index - self.window:
            self._offsets.popleft()
        self._index += 1
