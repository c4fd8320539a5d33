"""The camera's delay-based rate controller: the camera offers what the uplink carries. Pure.

The camera is most of what the drone sends, and it shares the UE's buffer with the state that closes the
control loop. At a fixed rate, a falling capacity first fills that buffer, the state's round trip grows
with it, and the supervisor throttles the camera only a dwell time later. A queue that builds shows
first in the one-way delay's growth, before any loss and before the round trip is high for long: that is
what WebRTC's delay-based congestion control (Google Congestion Control) reads, and aiortc ships its
estimator in pure Python (`aiortc.rate.RemoteBitrateEstimator`: inter-arrival groups, a Kalman filter on
the delay gradient, an over-use detector, AIMD rate control), used here as it is. Or, with `controller =
"queue"`, a queue-delay target (onboard/queue_rate.py): on cellular traces GCC held the camera far under
what the link carried; on one of three the target kept the supervisor's goodput at GCC's delay, on the
others it flew as GCC did (docs/camera.md).
This module is what both share: the feedback's checks, the timeout, and the factor.

The edge acks each image when its last part is in (edge/detector), saying when each part arrived by the
edge's clock; the drone knows when it handed each part to the link and its size. Only differences of
each clock are used, so the clocks need not agree. The estimator answers a target bitrate; the camera's
frame rate follows it: factor = target / (the bits of an image x the nominal frame rate), kept within
[`floor`, the supervisor's rate factor]. The supervisor's factor is a ceiling, so nothing here can make
the camera offer more than it would without the controller (docs/camera.md).

Bad feedback leaves the camera within those bounds. An ack for an image not sent (or forgotten), with
another number of parts, or with arrivals that are negative or out of order is refused and counted; an
ack older than one already read is stale and not read (the estimator wants arrivals in send order). An
arrival that runs backwards or jumps far ahead of its send times says the feedback's clock changed (a
detector replica took over): the estimator starts again and the target holds. Without a read ack for
`feedback_timeout_s`, the target halves every such timeout down to the floor (GCC without feedback).
"""

from __future__ import annotations

import itertools
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, cast

from dynqos.common.errors import ConfigError
from dynqos.onboard.queue_rate import PartAck, QueueDelayRate
from dynqos.onboard.trendline import TrendlineEstimator

NS_PER_MS = 1_000_000
ABS_SEND_TIME_UNITS = 1 << 18  # aiortc's (RTP's) abs-send-time: 6.18 fixed-point seconds, 24 bits
MAX_ARRIVAL_JUMP_NS = 10 * 1_000_000_000  # no UE buffer holds 10 s: a larger jump is another clock
BITS_EMA = 0.1  # weight of each image in the average image size


@dataclass(frozen=True, slots=True)
class PartSent:
    """One part of an image as the camera handed it to the link: when (drone clock) and its bytes on
    the link (payload and message header)."""

    sent_ns: int
    nbytes: int


@dataclass(slots=True)
class FeedbackCounts:
    read: int = 0  # acks whose parts went to the estimator
    refused: int = 0  # acks that contradict what was sent
    stale: int = 0  # acks older than one already read
    restarts: int = 0  # the feedback's clock changed: the estimator started again
    timeouts: int = 0  # feedback timeouts that halved the target


@dataclass(slots=True)
class DelayRateControl:
    """Turns the edge's arrival reports into the camera's rate factor (module docstring)."""

    nominal_fps: float
    floor: float = 0.25  # the least rate factor it sets (the supervisor's min_rate_factor)
    feedback_timeout_s: float = 1.0
    memory: int = 128  # images remembered for their acks
    delay_filter: str = "kalman"  # or "trendline" (onboard/trendline.py); GCC's
    controller: str = "gcc"  # aiortc's GCC, or "queue": a queue-delay target (onboard/queue_rate.py)
    queue_target_ms: float = 15.0  # "queue": the queue an image may meet before the rate comes down
    counts: FeedbackCounts = field(default_factory=FeedbackCounts)
    target_bps: float | None = None  # None: no estimate yet (the camera keeps the supervisor's rate)
    _images: OrderedDict[tuple[int, str], tuple[PartSent, ...]] = field(default_factory=OrderedDict)
    _frame_bits: dict[int, float] = field(default_factory=dict)
    _bits_per_frame: float | None = None
    _estimator: QueueDelayRate | GccRate | None = None
    _last_sent_ns: int | None = None  # the newest part read: later acks must be of later parts
    _last_arrival_ns: int | None = None
    _feedback_ns: int | None = None  # when an ack was last read, or the timeout last fired

    def __post_init__(self) -> None:
        if not self.nominal_fps > 0:
            raise ValueError(f"nominal_fps must be > 0, got {self.nominal_fps}")
        if not 0 < self.floor <= 1:
            raise ValueError(f"floor must be in (0, 1], got {self.floor}")
        if self.controller not in ("gcc", "queue"):
            raise ValueError(f'controller must be "gcc" or "queue", got {self.controller!r}')
        self._estimator = self._new_estimator()

    def _new_estimator(self) -> QueueDelayRate | GccRate:
        if self.controller == "queue":
            return QueueDelayRate(target_ms=self.queue_target_ms)
        return GccRate(new_estimator(self.delay_filter))

    def sent(self, seq: int, kind: str, parts: Sequence[PartSent]) -> None:
        """The camera handed image `seq` (`kind`) to the link in `parts`."""
        self._images[(seq, kind)] = tuple(parts)
        while len(self._images) > self.memory:
            self._images.popitem(last=False)
        bits = self._frame_bits.get(seq, 0.0) + 8.0 * sum(p.nbytes for p in parts)
        self._frame_bits[seq] = bits
        older = [s for s in self._frame_bits if s < seq]  # an image's bits are all in once the next is sent
        for done in older:
            whole = self._frame_bits.pop(done)
            self._bits_per_frame = (
                whole
                if self._bits_per_frame is None
                else (1 - BITS_EMA) * self._bits_per_frame + BITS_EMA * whole
            )

    def acked(
        self, seq: int, kind: str, arrival_ns: int, part_arrivals_us: Sequence[int], now_ns: int
    ) -> bool:
        """The edge's ack of image `seq`: its first part arrived at `arrival_ns` (edge clock), each part
        `part_arrivals_us` after that. True when it was read."""
        image = self._images.get((seq, kind))
        if image is None or not _consistent(image, arrival_ns, part_arrivals_us):
            self.counts.refused += 1
            return False
        if self._last_sent_ns is not None and image[0].sent_ns <= self._last_sent_ns:
            self.counts.stale += 1
            return False
        del self._images[(seq, kind)]
        if self._clock_changed(image[0].sent_ns, arrival_ns):
            self._estimator = self._new_estimator()
            self.counts.restarts += 1
        arrivals = [arrival_ns + offset_us * 1000 for offset_us in part_arrivals_us]
        self._estimate(image, arrivals)
        self._last_sent_ns = image[-1].sent_ns
        self._last_arrival_ns = arrivals[-1]
        self._feedback_ns = now_ns
        self.counts.read += 1
        return True

    def _estimate(self, image: tuple[PartSent, ...], arrivals: list[int]) -> None:
        """Hand an image's parts, sent and arrived, to the controller; keep the target it answers."""
        assert self._estimator is not None  # made in __post_init__
        acks = [
            PartAck(part.sent_ns, arrived, part.nbytes) for part, arrived in zip(image, arrivals, strict=True)
        ]
        target = self._estimator.image(acks)
        self.target_bps = self.target_bps if target is None else target

    def _clock_changed(self, sent_ns: int, arrival_ns: int) -> bool:
        if self._last_arrival_ns is None or self._last_sent_ns is None:
            return False
        ahead = (arrival_ns - self._last_arrival_ns) - (sent_ns - self._last_sent_ns)
        return arrival_ns < self._last_arrival_ns or ahead > MAX_ARRIVAL_JUMP_NS

    def factor(self, ceiling: float, now_ns: int) -> float:
        """The camera's rate factor now: the target's share of the nominal rate, in [floor, ceiling]."""
        self._time_out(now_ns)
        if ceiling <= 0:
            return ceiling  # the supervisor stopped the camera
        if self.target_bps is None or self._bits_per_frame is None:
            return ceiling
        wanted = self.target_bps / (self._bits_per_frame * self.nominal_fps)
        return max(min(self.floor, ceiling), min(ceiling, wanted))

    def _time_out(self, now_ns: int) -> None:
        if self._feedback_ns is None:
            self._feedback_ns = now_ns  # the timeout runs from the first question
            return
        timeout_ns = round(self.feedback_timeout_s * 1e9)
        while now_ns - self._feedback_ns >= timeout_ns:
            self._feedback_ns += timeout_ns
            self.counts.timeouts += 1
            if self._bits_per_frame is None:
                continue  # nothing sent yet: nothing to slow
            least = self.floor * self._bits_per_frame * self.nominal_fps
            start = (
                self.target_bps if self.target_bps is not None else self._bits_per_frame * self.nominal_fps
            )
            self.target_bps = max(least, start / 2)


def _consistent(image: tuple[PartSent, ...], arrival_ns: int, part_arrivals_us: Sequence[int]) -> bool:
    """The ack describes this image: one arrival per part, the first at its base, none going back."""
    if len(part_arrivals_us) != len(image) or arrival_ns <= 0 or part_arrivals_us[0] != 0:
        return False
    return all(b >= a for a, b in itertools.pairwise(part_arrivals_us))


@dataclass(slots=True)
class GccRate:
    """aiortc's estimator behind the queue-delay target's interface: an image's parts in, a target out
    (None while it has none)."""

    estimator: Any

    def image(self, parts: Sequence[PartAck]) -> float | None:
        target = None
        for part in parts:
            arrived_ms = part.arrived_ns // NS_PER_MS
            answer = self.estimator.add(arrived_ms, abs_send_time(part.sent_ns), part.nbytes, 0)
            if answer is not None:
                target = float(answer[0])
        return target


def check_installed(rate_control: str, controller: str) -> None:
    """A ConfigError naming the extra when the settings need aiortc and it is missing (GCC does; the
    queue-delay target and no controller do not), so a daemon says so before it opens any network."""
    if rate_control == "delay" and controller == "gcc":
        new_estimator()


def abs_send_time(sent_ns: int) -> int:
    """`sent_ns` as RTP's abs-send-time (24-bit, 6.18 fixed-point seconds; the estimator's wrap)."""
    return (sent_ns * ABS_SEND_TIME_UNITS // 1_000_000_000) & 0xFFFFFF


def new_estimator(delay_filter: str = "kalman") -> Any:
    """aiortc's port of WebRTC's receive-side delay-based estimator (with libwebrtc's trendline filter
    in place of its Kalman filter for "trendline"), or a ConfigError that says how to install it
    (`[onboard] camera_rate_control = "delay"` needs it; the default, "none", does not)."""
    try:
        from aiortc.rate import RemoteBitrateEstimator
    except ImportError as exc:
        raise ConfigError(
            "onboard.camera_rate_control",
            f'"delay" needs aiortc ({exc}): pip install "dynqos[camera-rate]"',
        ) from exc
    estimator = RemoteBitrateEstimator()
    if delay_filter == "trendline":
        estimator.estimator = cast(Any, TrendlineEstimator())  # aiortc's OveruseEstimator interface
    elif delay_filter != "kalman":
        raise ValueError(f'delay_filter must be "kalman" or "trendline", got {delay_filter!r}')
    return estimator
