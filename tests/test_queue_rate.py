"""The camera's queue-delay target (onboard/queue_rate.py): it climbs while images meet no queue, comes
down to what the link delivered while they meet one longer than the target, takes a link that delivers
in bursts without keeping a queue for a free one, and reads only differences of each clock."""

from __future__ import annotations

import itertools

import pytest

from dynqos.onboard.queue_rate import PartAck, QueueDelayRate

MS = 1_000_000
PART = 4096


def _images(
    control: QueueDelayRate,
    seconds: float,
    *,
    link_bps: float,
    fps: float = 15.0,
    parts: int = 8,
    start_ns: int = 0,
    offset_ns: int = 0,
    gap_every_ms: int = 0,
    gap_ms: int = 0,
) -> list[float | None]:
    """Images of `parts` x 4 kB sent at `fps` through a FIFO of `link_bps` (held for `gap_ms` every
    `gap_every_ms`, the link's transmit opportunities); each image acked when its last part is in, its
    arrivals read on a clock `offset_ns` ahead. The targets answered, one per image."""
    free_ns = start_ns  # when the link is next free
    answers = []
    for n in range(int(seconds * fps)):
        sent = start_ns + round(n * 1e9 / fps)
        acks = []
        for _ in range(parts):
            begin = max(sent, free_ns)
            if gap_every_ms and (begin // MS) % gap_every_ms < gap_ms:
                begin += (gap_ms - (begin // MS) % gap_every_ms) * MS  # held until the gap ends
            free_ns = begin + round(8 * PART / link_bps * 1e9)
            acks.append(PartAck(sent, free_ns + offset_ns, PART))
        answers.append(control.image(acks))
    return answers


def test_an_empty_queue_lets_the_target_climb_but_not_past_twice_what_arrived() -> None:
    control = QueueDelayRate()
    offered = 15 * 8 * PART * 8  # 3.9 Mbit/s, on a link of 40: no queue
    answers = _images(control, 3.0, link_bps=40e6)
    targets = [a for a in answers if a is not None]
    assert targets[0] == pytest.approx(offered, rel=0.3)  # the first: what arrived
    assert targets[-1] > 1.5 * offered  # it climbed
    assert max(targets) <= 2 * offered * 1.1  # bounded by what the link showed it carries
    assert control.queue_ms is not None
    assert control.queue_ms < 5


def test_a_standing_queue_brings_the_target_down_to_what_the_link_delivered() -> None:
    """The link falls from 40 to 2 Mbit/s under a camera that offers 3.9: the queue grows about half a
    second each second, and within a second of the fall the target is at most what the link delivers,
    however high it had climbed."""
    control = QueueDelayRate(target_ms=15)
    climbed = _images(control, 3.0, link_bps=40e6)[-1]
    assert climbed is not None
    assert climbed > 6e6
    answers = _images(control, 3.0, link_bps=2e6, start_ns=3 * 10**9)
    assert control.queue_ms is not None
    assert control.queue_ms > 15
    late = answers[15:]  # a second after the fall (15 images)
    assert all(a is not None and a <= 2e6 * 1.05 for a in late)


def test_a_link_that_delivers_in_bursts_without_keeping_a_queue_reads_as_free() -> None:
    """Transmit opportunities that pause 30 ms of every 40 (a cellular uplink's grants) hold images for
    up to 30 ms, more than the target, but the queue empties between them: the target keeps climbing,
    as on an even link."""
    bursty, even = QueueDelayRate(target_ms=15), QueueDelayRate(target_ms=15)
    held = [a for a in _images(bursty, 3.0, link_bps=40e6, gap_every_ms=40, gap_ms=30) if a is not None]
    steady = [a for a in _images(even, 3.0, link_bps=40e6) if a is not None]
    assert all(b >= a for a, b in itertools.pairwise(held))  # it never came down
    assert held[-1] >= 0.9 * steady[-1]


def test_the_clocks_offset_changes_nothing() -> None:
    same, ahead = QueueDelayRate(), QueueDelayRate()
    queued = _images(same, 3.0, link_bps=2e6)
    shifted = _images(ahead, 3.0, link_bps=2e6, offset_ns=-(10**12))  # the edge's clock 1000 s behind
    assert queued == shifted


def test_the_queue_counts_from_the_links_own_delay_which_the_least_delay_keeps() -> None:
    """A link whose own delay is 40 ms and that keeps no queue: the images meet none (the base is the
    least delay seen, not zero)."""
    control = QueueDelayRate(target_ms=20)
    answers = _images(control, 2.0, link_bps=40e6, offset_ns=40 * MS)
    assert control.queue_ms is not None
    assert control.queue_ms < 5
    targets = [a for a in answers if a is not None]
    assert targets[-1] > targets[0]  # it climbed: 40 ms of the link's own delay is not a queue


def test_an_image_without_parts_changes_nothing() -> None:
    control = QueueDelayRate()
    assert control.image([]) is None
    _images(control, 1.0, link_bps=40e6)
    before = control.target_bps
    assert control.image([]) == before
