"""Camera pacing: hand a frame to the link in parts spread over time, not in one burst. Pure.

A bearer is a FIFO. A 40 kB depth frame handed over at once sits in front of every state that
follows it until the cell has drained it: at 65 Mbit/s that is 5 ms per frame at full scale, and the
same ~50 ms at any scale, since frames and rates scale together. Sent as parts no faster than the bearer
drains them, a frame never queues in it, and a state waits at most for the one part in service. The
frame still arrives about as soon as it would have in one burst, because the bearer was the bottleneck
anyway. WebRTC's pacer does the same for video packets.
"""

from __future__ import annotations

from dynqos.common.clock import NS_PER_S

FRAME_HEADER_BYTES = 200  # one CameraFrame message on the link besides its payload (msgpack ~190, zenoh)


def split(payload: bytes, part_bytes: int) -> list[bytes]:
    """The payload in parts of at most `part_bytes` (one empty part for an empty payload)."""
    if part_bytes <= 0:
        raise ValueError(f"part_bytes must be > 0, got {part_bytes}")
    if not payload:
        return [b""]
    return [payload[i : i + part_bytes] for i in range(0, len(payload), part_bytes)]


class Pacer:
    """Reserves the link at `rate_bps`: each send waits until the bytes before it have gone out.

    `reserve(nbytes, now_ns)` returns how long to wait before sending; the first send after a quiet
    spell goes at once. There is no saved-up credit, so the link never sees more than one part ahead of
    the pace.
    """

    def __init__(self, rate_bps: float) -> None:
        if not rate_bps > 0:
            raise ValueError(f"rate_bps must be > 0, got {rate_bps}")
        self.rate_bps = rate_bps
        self._busy_until_ns = 0

    def reserve(self, nbytes: int, now_ns: int) -> int:
        start = max(self._busy_until_ns, now_ns)
        self._busy_until_ns = start + round(nbytes * 8 * NS_PER_S / self.rate_bps)
        return start - now_ns
