"""A queue-delay target for the camera's rate: slow to what the link delivered while a queue stands,
climb fast while none does. Pure.

GCC (aiortc's port) held the camera far under what cellular traces carry: on over-use it sets the target
to 0.85 x the rate received over the last second, which in a fade is the fade's rate, and climbs back
from there by about one packet per round trip. Flown on the three LTE traces it carried 0.19-0.63 of
them with either delay filter (docs/camera.md). This controller follows Ericsson's SCReAM v2 instead: a
queue is allowed up to a target delay, and what decides is how long the queue makes an image wait, not
the delay's gradient, so a link that delivers in bursts without keeping a queue reads as free.

It reads each image's parts as the edge acked them: when each was handed to the link (drone clock) and
when it arrived (edge clock). Their difference is the one-way delay plus the clocks' offset; its least
value over `base_window_s` is the link's own delay, and what an image's first part spent above it is the
queue the image met (its later parts also wait for the image's own earlier parts). The queue that counts
is the least one the images sent over the last `queue_window_s` met: a cellular uplink's transmit
opportunities come tens of milliseconds apart and hold an image now and then, a queue that stands holds
them all. Each image then moves the target at most every `update_interval_s`:

- queue over `target_ms`: down to what the link delivered over the last `rate_window_s` (while a queue
  stands that is the link's capacity), less the share that drains the excess in about one target
  (at least half of it kept);
- queue under `target_ms`: up by `ramp_per_s` x the time since the last change, in proportion to the
  room left under the target, and never past twice what the link delivered (an idle link's rate says
  nothing of its capacity beyond that).

The clocks' offset cancels: only differences of the same clock's readings are used (SCReAM, and the
drone's own feedback checks in onboard/camera_rate.py, which also refuse bad acks before they get here).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000
BASE_BUCKET_NS = NS_PER_S  # the base delay is kept as one least value per second of sending


@dataclass(frozen=True, slots=True)
class PartAck:
    """One part of an image: sent (drone clock), arrived (edge clock), its bytes on the link."""

    sent_ns: int
    arrived_ns: int
    nbytes: int


@dataclass(slots=True)
class QueueDelayRate:
    """The camera's target bitrate from its images' queueing delay (module docstring)."""

    target_ms: float = 15.0  # the queue an image may meet before the rate comes down
    ramp_per_s: float = 2.0  # the increase per second on an empty queue, as a share of the rate
    update_interval_s: float = 0.1  # the least time between two changes of the target
    rate_window_s: float = 0.5  # the span the delivered rate is measured over (edge clock)
    base_window_s: float = 30.0  # the span the link's own delay is the least one-way delay over
    queue_window_s: float = 0.2  # the queue that counts is the least the images sent over this span met
    target_bps: float | None = None
    queue_ms: float | None = None  # the queue that counts now (the least of the last queue_window_s)
    _bases: deque[tuple[int, int]] = field(default_factory=deque)  # (bucket, least delay) by sending
    _arrivals: deque[tuple[int, int]] = field(default_factory=deque)  # (arrived, bytes), edge clock
    _window_bytes: int = 0
    _first_arrival_ns: int | None = None
    _changed_ns: int | None = None  # when the target last changed (drone clock, of the image's send)
    _queues: deque[tuple[int, int]] = field(default_factory=deque)  # (sent, queue) of recent images

    def image(self, parts: Sequence[PartAck]) -> float | None:
        """An image's parts, acked, in the order sent; the target bitrate (None before the first)."""
        if not parts:
            return self.target_bps
        if self._first_arrival_ns is None:
            self._first_arrival_ns = parts[0].arrived_ns
        for part in parts:
            self._note_base(part.sent_ns, part.arrived_ns - part.sent_ns)
            self._arrivals.append((part.arrived_ns, part.nbytes))
            self._window_bytes += part.nbytes
        newest = parts[-1].arrived_ns
        while self._arrivals and self._arrivals[0][0] <= newest - round(self.rate_window_s * NS_PER_S):
            self._window_bytes -= self._arrivals.popleft()[1]
        first = parts[0]
        self._queues.append((first.sent_ns, (first.arrived_ns - first.sent_ns) - self._base()))
        while self._queues[0][0] < first.sent_ns - round(self.queue_window_s * NS_PER_S):
            self._queues.popleft()
        self.queue_ms = min(queue for _, queue in self._queues) / NS_PER_MS
        delivered = self.delivered_bps()
        if delivered is None:
            return self.target_bps
        now = parts[-1].sent_ns
        if self.target_bps is None or self._changed_ns is None:
            self.target_bps, self._changed_ns = delivered, now
            return self.target_bps
        since_s = (now - self._changed_ns) / NS_PER_S
        if since_s < self.update_interval_s:
            return self.target_bps
        self.target_bps = self._next(self.target_bps, delivered, self.queue_ms, min(since_s, 1.0))
        self._changed_ns = now
        return self.target_bps

    def _next(self, rate: float, delivered: float, queue_ms: float, since_s: float) -> float:
        if queue_ms > self.target_ms:
            excess = (queue_ms - self.target_ms) / self.target_ms
            return min(rate, delivered * max(0.5, 1.0 - 0.5 * excess))
        room = 1.0 - queue_ms / self.target_ms
        return min(rate * (1.0 + self.ramp_per_s * since_s * room), max(rate, 2.0 * delivered))

    def delivered_bps(self) -> float | None:
        """What arrived over the last `rate_window_s` (bits/s); None until arrivals span that long (a
        shorter span reads an image's burst for a rate)."""
        if not self._arrivals or self._first_arrival_ns is None:
            return None
        window_ns = round(self.rate_window_s * NS_PER_S)
        if self._arrivals[-1][0] - self._first_arrival_ns < window_ns:
            return None
        return 8.0 * self._window_bytes * NS_PER_S / window_ns

    def _note_base(self, sent_ns: int, delay_ns: int) -> None:
        bucket = sent_ns // BASE_BUCKET_NS
        if self._bases and self._bases[-1][0] == bucket:
            if delay_ns < self._bases[-1][1]:
                self._bases[-1] = (bucket, delay_ns)
        else:
            self._bases.append((bucket, delay_ns))
        while self._bases and self._bases[0][0] <= bucket - round(self.base_window_s):
            self._bases.popleft()

    def _base(self) -> int:
        return min(delay for _, delay in self._bases)
