"""The camera's delay-based rate controller (onboard/camera_rate.py): what it makes of good and bad
feedback, and, on a link whose capacity follows a real LTE uplink trace, that it keeps the queue in front
of the state short where a fixed rate fills it, while carrying most of what the trace could."""

from __future__ import annotations

import statistics
import sys
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from dynqos.common.errors import ConfigError
from dynqos.onboard.camera import RateController
from dynqos.onboard.camera_rate import DelayRateControl, PartSent, abs_send_time
from dynqos.sim.network.traces import Trace

MS = 1_000_000
TRACES = Path(__file__).resolve().parents[2] / "shared" / "data" / "traces"


@pytest.fixture(params=["gcc", "queue"])
def controller(request: pytest.FixtureRequest) -> str:
    """Each controller the feedback goes to (`[onboard] camera_rate_controller`): bad feedback is
    refused before either sees it, and a missing one slows the camera the same way."""
    return str(request.param)


def _image(control: DelayRateControl, seq: int, sent_ns: int, parts: int = 4, nbytes: int = 4096) -> None:
    control.sent(seq, "rgb", [PartSent(sent_ns + i * MS, nbytes) for i in range(parts)])


def test_abs_send_time_is_rtps_24_bit_fixed_point_seconds() -> None:
    assert abs_send_time(0) == 0
    assert abs_send_time(1_000_000_000) == 1 << 18
    assert abs_send_time(64 * 1_000_000_000) == 0  # wraps every 64 s, as the estimator expects


def test_without_an_estimate_the_camera_keeps_the_supervisors_rate(controller: str) -> None:
    control = DelayRateControl(15.0, controller=controller)
    assert control.factor(1.0, 0) == 1.0
    assert control.factor(0.5, 1) == 0.5
    assert control.factor(0.0, 2) == 0.0  # the supervisor stopped the camera


def test_acks_that_contradict_what_was_sent_are_refused_and_change_nothing(controller: str) -> None:
    control = DelayRateControl(15.0, controller=controller)
    _image(control, 1, 0)
    bad = [
        (2, "rgb", 5 * MS, (0, 100, 200, 300)),  # an image never sent (forged)
        (1, "depth", 5 * MS, (0, 100, 200, 300)),  # the other kind
        (1, "rgb", 5 * MS, (0, 100, 200)),  # a part missing
        (1, "rgb", 5 * MS, (0, 300, 200, 400)),  # arrivals going back
        (1, "rgb", 5 * MS, (10, 100, 200, 300)),  # not from the first part's arrival
        (1, "rgb", 0, (0, 100, 200, 300)),  # no arrival at all
    ]
    for seq, kind, arrival, offsets in bad:
        assert not control.acked(seq, kind, arrival, offsets, 10 * MS)
    assert control.counts.refused == len(bad)
    assert control.counts.read == 0
    assert control.acked(1, "rgb", 5 * MS, (0, 100, 200, 300), 10 * MS)
    assert not control.acked(1, "rgb", 5 * MS, (0, 100, 200, 300), 10 * MS)  # once only
    assert control.counts.read == 1


def test_an_ack_older_than_one_read_is_stale(controller: str) -> None:
    control = DelayRateControl(15.0, controller=controller)
    _image(control, 1, 0)
    _image(control, 2, 66 * MS)
    assert control.acked(2, "rgb", 80 * MS, (0, 1000, 2000, 3000), 90 * MS)
    assert not control.acked(1, "rgb", 10 * MS, (0, 1000, 2000, 3000), 91 * MS)  # reordered: not read
    assert control.counts.stale == 1


def test_a_feedback_clock_that_jumps_restarts_the_estimator_and_the_target_holds(controller: str) -> None:
    control = DelayRateControl(15.0, controller=controller)
    _image(control, 1, 0)
    assert control.acked(1, "rgb", 5 * MS, (0, 1000, 2000, 3000), 10 * MS)
    control.target_bps = 3e6
    _image(control, 2, 66 * MS)
    assert control.acked(2, "rgb", 1 * MS, (0, 1000, 2000, 3000), 80 * MS)  # backwards: another detector
    _image(control, 3, 133 * MS)
    assert control.acked(3, "rgb", 60_000 * MS, (0, 1000, 2000, 3000), 150 * MS)  # a minute ahead
    assert control.counts.restarts == 2
    assert control.target_bps == 3e6


def test_after_a_clock_jump_the_queue_target_reads_the_new_clock_not_a_queue() -> None:
    """A detector replica whose clock is a minute ahead: the queue-delay target starts again, so on a
    free link it follows what arrives. Kept from the old clock, its least delay would read the minute as
    a queue and halve the camera."""
    control = DelayRateControl(15.0, controller="queue")
    period = 66 * MS
    for seq in range(1, 41):  # 2.6 s of images of 4 x 4 kB (2 Mbit/s), each acked 5 ms after it left
        jump = 60_000 * MS if seq > 20 else 0
        _image(control, seq, seq * period)
        assert control.acked(seq, "rgb", seq * period + 5 * MS + jump, (0, 1000, 2000, 3000), seq * period)
    assert control.counts.restarts == 1
    assert control.target_bps is not None
    assert control.target_bps >= 1.5e6


def test_without_feedback_the_rate_halves_each_timeout_down_to_the_floor(controller: str) -> None:
    control = DelayRateControl(10.0, floor=0.25, feedback_timeout_s=1.0, controller=controller)
    for seq in range(1, 4):  # 3 images of 4 x 4096 B: the average image once the next is sent
        _image(control, seq, seq * 100 * MS)
    assert control.factor(1.0, 0) == 1.0  # the timeout runs from here
    assert control.factor(1.0, 999 * MS) == 1.0
    assert control.factor(1.0, 1000 * MS) == pytest.approx(0.5)
    assert control.factor(0.4, 1500 * MS) == pytest.approx(0.4)  # the supervisor's factor is a ceiling
    assert control.factor(1.0, 2000 * MS) == pytest.approx(0.25)
    assert control.factor(1.0, 9000 * MS) == pytest.approx(0.25)  # never below the floor
    assert control.factor(0.1, 9000 * MS) == pytest.approx(0.1)  # ...unless the supervisor's is lower
    assert control.counts.timeouts == 9


def test_the_queue_delay_target_needs_no_aiortc(monkeypatch: pytest.MonkeyPatch) -> None:
    """`dynqos[onboard]` without the camera-rate extra: GCC is refused with the extra's name, the
    queue-delay target (onboard/queue_rate.py) runs and answers a target."""
    monkeypatch.setitem(sys.modules, "aiortc.rate", None)  # `from aiortc.rate import ...` fails
    with pytest.raises(ConfigError, match=r"dynqos\[camera-rate\]"):
        DelayRateControl(15.0)
    control = DelayRateControl(15.0, controller="queue")
    for seq in range(1, 16):  # a second of images over a free link
        _image(control, seq, seq * 66 * MS)
        assert control.acked(
            seq, "rgb", seq * 66 * MS + 5 * MS, (0, 1000, 2000, 3000), seq * 66 * MS + 9 * MS
        )
    assert control.target_bps is not None
    with pytest.raises(ValueError, match="controller"):
        DelayRateControl(15.0, controller="scream")


# ---- on a real uplink trace -------------------------------------------------------------------------


@dataclass
class _Part:
    image: int
    index: int
    bits: float
    sent_ns: int


@dataclass
class _Link:
    """A FIFO whose capacity each millisecond is the trace's (sim/network/traces.py), drop-tail at
    `buffer_bits`, and a 10 ms downlink for the acks."""

    trace: Trace
    buffer_bits: float
    queue: deque[_Part] = field(default_factory=deque)
    queued_bits: float = 0.0
    credit: float = 0.0
    carried_bits: float = 0.0
    capacity_bits: float = 0.0
    dropped: set[int] = field(default_factory=set)

    def offer(self, part: _Part) -> None:
        if self.queued_bits + part.bits > self.buffer_bits:
            self.dropped.add(part.image)
            return
        self.queue.append(part)
        self.queued_bits += part.bits

    def serve(self, t_ms: int) -> list[_Part]:
        grant = self.trace.bits_between(t_ms / 1000, (t_ms + 1) / 1000)
        self.capacity_bits += grant
        self.credit += grant
        done = []
        while self.queue and self.credit >= self.queue[0].bits:
            part = self.queue.popleft()
            self.credit -= part.bits
            self.queued_bits -= part.bits
            self.carried_bits += part.bits
            done.append(part)
        if not self.queue:
            self.credit = min(self.credit, 0.0)  # an idle link saves nothing up
        return done


def _fly(trace: Trace, control: DelayRateControl | None, seconds: int = 90) -> tuple[list[float], float]:
    """A 15 frames/s camera of 12 parts of 4 kB (plus headers) per image over the trace's link: each
    image's delay (its last part's arrival after its capture, ms) and the share of the trace's capacity
    the link carried."""
    fps, parts, part_bits = 15.0, 12, (4096 + 200) * 8
    link = _Link(trace, buffer_bits=2.0 * trace.mean_mbps() * 1e6)  # 2 s of the mean rate
    rate = RateController(fps)
    arrived: dict[int, list[int]] = {}
    acks: deque[tuple[int, int, tuple[int, int, tuple[int, ...]]]] = deque()
    delays: list[float] = []
    seq = 0
    for t_ms in range(seconds * 1000):
        now = t_ms * MS
        while acks and acks[0][0] <= t_ms:
            _, image, (first, _, offsets) = acks.popleft()
            if control is not None:
                control.acked(image, "rgb", first, offsets, now)
        rate.factor = 1.0 if control is None else control.factor(1.0, now)
        if rate.due(now):
            seq += 1
            sent = [PartSent(now, part_bits // 8) for _ in range(parts)]
            if control is not None:
                control.sent(seq, "rgb", sent)
            for index in range(parts):
                link.offer(_Part(seq, index, part_bits, now))
        for part in link.serve(t_ms):
            times = arrived.setdefault(part.image, [])
            times.append(now + MS)
            if len(times) == parts and part.image not in link.dropped:
                delays.append((now + MS - part.sent_ns) / MS)
                offsets = tuple((t - times[0]) // 1000 for t in times)
                acks.append((t_ms + 10, part.image, (times[0], 0, offsets)))
    return delays[len(delays) // 3 :], link.carried_bits / link.capacity_bits  # after the start-up


@pytest.mark.parametrize("name", ["ATT-LTE-driving-2016.up", "TMobile-LTE-short.up", "Verizon-LTE-short.up"])
def test_on_a_real_lte_uplink_the_controller_keeps_most_images_out_of_the_queue(name: str) -> None:
    """The camera offers 6.2 Mbit/s; the trace is scaled to a mean of 5, so at a fixed rate the queue
    fills toward the UE's buffer and a typical image waits seconds behind it. With the controller the
    median image's delay is at least 3x lower (measured: 1485 -> 354, 1780 -> 116, 420 -> 131 ms) and the
    link carries about half of what the trace granted (0.51-0.53): GCC's slow ramp after a decrease and
    the floor's rate in the traces' deep fades. Its p95 stays in those fades (docs/camera.md)."""
    path = TRACES / name
    if not path.exists():
        pytest.skip(f"the LTE traces are not here ({path})")
    fixed_delays, fixed_share = _fly(Trace.load(path, mean_mbps=5.0), None)
    control = DelayRateControl(15.0, floor=0.25)
    delays, share = _fly(Trace.load(path, mean_mbps=5.0), control)
    p50, fixed_p50 = statistics.median(delays), statistics.median(fixed_delays)
    print(
        f"{name}: image delay p50 {fixed_p50:.0f} -> {p50:.0f} ms, carried {fixed_share:.2f} -> {share:.2f}"
    )
    assert p50 * 3 <= fixed_p50
    assert share >= 0.45
    assert control.counts.read > 300  # it read the acks: about 4 images a second at the floor
    assert control.counts.refused == control.counts.stale == 0


@pytest.mark.parametrize("name", ["ATT-LTE-driving-2016.up", "TMobile-LTE-short.up", "Verizon-LTE-short.up"])
def test_on_the_bare_link_the_trendline_filter_carries_more_than_the_kalman_filter(name: str) -> None:
    """The same link and camera as above with libwebrtc's trendline filter (onboard/trendline.py): it
    carries more of the trace (measured 0.78 on each, against the Kalman filter's 0.51-0.53), at an
    image delay still below the fixed rate's (p50 181, 132, 238 ms against 1485, 1780, 420; on Verizon
    it queues longer than the Kalman filter's 131). In flight the two carry the same (docs/camera.md)."""
    path = TRACES / name
    if not path.exists():
        pytest.skip(f"the LTE traces are not here ({path})")
    fixed_delays, _ = _fly(Trace.load(path, mean_mbps=5.0), None)
    _, kalman_share = _fly(Trace.load(path, mean_mbps=5.0), DelayRateControl(15.0, floor=0.25))
    control = DelayRateControl(15.0, floor=0.25, delay_filter="trendline")
    delays, share = _fly(Trace.load(path, mean_mbps=5.0), control)
    p50, fixed_p50 = statistics.median(delays), statistics.median(fixed_delays)
    print(f"{name}: trendline carried {share:.2f} (Kalman {kalman_share:.2f}), image delay p50 {p50:.0f} ms")
    assert share >= 0.7
    assert share >= kalman_share + 0.15
    assert p50 < fixed_p50


@pytest.mark.parametrize("name", ["ATT-LTE-driving-2016.up", "TMobile-LTE-short.up", "Verizon-LTE-short.up"])
def test_on_the_bare_link_the_queue_delay_target_trades_image_delay_for_goodput(name: str) -> None:
    """The same link and camera with the queue-delay target (onboard/queue_rate.py). At its default
    15 ms the median image waits at least 3x less than at the fixed rate (measured p50 116, 122, 105 ms
    against 1485, 1780, 420) and the link carries 0.39, 0.79, 0.69 of the trace (GCC: 0.51-0.53); at
    50 ms it carries more (0.66, 0.87, 0.75) and the median image waits longer (147, 162, 145 ms).
    docs/camera.md says what the flights made of the two."""
    path = TRACES / name
    if not path.exists():
        pytest.skip(f"the LTE traces are not here ({path})")
    fixed_delays, _ = _fly(Trace.load(path, mean_mbps=5.0), None)
    figures = {}
    for target_ms in (15.0, 50.0):
        control = DelayRateControl(15.0, floor=0.25, controller="queue", queue_target_ms=target_ms)
        delays, share = _fly(Trace.load(path, mean_mbps=5.0), control)
        figures[target_ms] = (statistics.median(delays), share)
        assert control.counts.refused == control.counts.stale == 0
    (p50, share), (p50_50, share_50) = figures[15.0], figures[50.0]
    fixed_p50 = statistics.median(fixed_delays)
    print(f"{name}: target 15 ms carried {share:.2f}, p50 {p50:.0f} ms; 50 ms {share_50:.2f}, {p50_50:.0f}")
    assert p50 * 3 < fixed_p50
    assert share >= 0.35
    assert share_50 >= share + 0.05
    assert p50_50 > p50
