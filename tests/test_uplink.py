"""The onboard uplink through the emulated cell while coverage is lost: a real zenoh link that backs up.

A put with zenoh's BLOCK congestion control waits while the link is backed up (up to 5 s, zenoh's
`wait_before_close`); the daemon's tick must not. These tests back a drone's link up for real: the
cell carries nothing while coverage is lost, a bulk publisher fills the cell's buffer and the sockets
behind it, and a BLOCK put on a side thread shows that the link is blocked.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.bus import Publisher
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received
from dynqos.onboard.daemon import STREAMS
from dynqos.onboard.uplink import Uplink
from tests.cellrig import ZenohThroughCell, zenoh_through_cell

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

UAV = "uav7"
PROBE_SEQ = 1_000_000
FILL_BYTES = 64 * 1024
FILL_MAX_PUTS = 2000  # bounded: at most 128 MB offered, and at most FILL_MAX_S
FILL_MAX_S = 1.5
# Shorter than zenoh's wait_before_close (5 s): a put blocked longer closes the link, and what is put
# before the drone reconnects has no route.
LOSS_S = 4.0


def _state(seq: int) -> State:
    return State(uav=UAV, seq=seq, stamp_ns=seq, pos_m=(0, 0, -1), vel_mps=(0, 0, 0), quat=(1, 0, 0, 0))


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[ZenohThroughCell]:
    with zenoh_through_cell(tmp_path, UAV, "scale = 10\nue_buffer_bytes = 200000") as rig:
        yield rig


def _state_publisher(rig: ZenohThroughCell) -> Publisher:
    """The drone's state publisher on the priority flow, as the daemon declares it: REAL_TIME, BLOCK,
    express (each state its own batch, so zenoh's one-batch REAL_TIME queue fills at the second)."""
    _, priority, drop = STREAMS[Stream.STATE]
    return rig.drone.publisher(
        keys.uplink(UAV, Flow.PRIORITY, Stream.STATE), priority, drop_when_congested=drop, express=not drop
    )


def _back_up(rig: ZenohThroughCell, loss_s: float) -> threading.Event:
    """Lose coverage for `loss_s` and fill the priority flow's link until a state put waits on it; the
    event is set when that put returns."""
    camera = keys.uplink(UAV, Flow.PRIORITY, Stream.CAMERA_RGB)
    bulk = rig.drone.publisher(camera, STREAMS[Stream.CAMERA_RGB][1], drop_when_congested=True)
    rig.edge.subscribe(camera, BoundedQueue(4))
    # zenoh drops what no subscriber matches at the source; the subscription crosses the cell, so
    # before the coverage goes
    assert bulk.wait_matched(10)
    assert rig.cell.post_event({"kind": "coverage_loss", "duration_s": loss_s})[0] == 200
    probe = _state_publisher(rig)
    returned = threading.Event()

    def blocking_put() -> None:
        for _ in range(3):
            probe.put(_state(PROBE_SEQ))
        returned.set()

    filler = b"\0" * FILL_BYTES
    deadline = time.monotonic() + FILL_MAX_S
    for _ in range(FILL_MAX_PUTS):
        if time.monotonic() > deadline:
            break
        bulk.put_bytes(filler)
    threading.Thread(target=blocking_put, daemon=True).start()
    return returned


def test_a_blocked_flow_never_holds_the_caller_and_its_newest_message_gets_through(
    rig: ZenohThroughCell,
) -> None:
    arrived: BoundedQueue[Received] = BoundedQueue(1000)
    rig.edge.subscribe(keys.uplink_any_flow(UAV, Stream.STATE), arrived)
    stop = threading.Event()
    uplink = Uplink(stop, depth=8)
    uplink.start()
    state = _state_publisher(rig)
    try:
        returned = _back_up(rig, loss_s=LOSS_S)
        # The link is blocked for real: a BLOCK put on it has not come back.
        assert not returned.wait(1.0), "the filler did not back the link up; nothing was tested"
        for seq in range(100):  # two seconds of 50 Hz states, all handed over while the link is blocked
            uplink.put(Flow.PRIORITY, state, _state(seq))
        assert not returned.is_set(), "the link came back before every state was handed over"
        assert uplink.pending() <= 8 * 2
        assert uplink.dropped >= 100 - 8 - 1  # the queue kept its bound (one may be in the sender's put)
        # Coverage comes back: the blocked put and the newest state are delivered; nothing else waits.
        assert returned.wait(30.0)
        seqs: set[int] = set()
        while 99 not in seqs:
            got = arrived.get(timeout_s=30.0)
            assert got is not None, f"the newest state never arrived (got {sorted(seqs)})"
            seqs.add(got.message.seq)  # type: ignore[attr-defined]
        assert not seqs & set(range(1, 99 - 8)), "states older than the queue's bound were delivered"
    finally:
        stop.set()
        uplink.join(timeout_s=10)
