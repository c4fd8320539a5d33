"""Paced camera frames: the onboard pacer and splitter, the detector's reassembly, the message contract."""

from __future__ import annotations

import random
from dataclasses import fields, replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynqos.common.errors import DecodeError, MessageError
from dynqos.common.messages import CameraFrame, decode, encode
from dynqos.edge.detector.assembler import FrameAssembler
from dynqos.onboard.pacing import Pacer, split

MS = 1_000_000


def frame(seq: int, payload: bytes, *, uav: str = "uav1", kind: str = "depth", stamp: int = 0) -> CameraFrame:
    return CameraFrame(uav=uav, seq=seq, stamp_ns=stamp or seq * 66 * MS, kind=kind, encoding="zstd16",
                       width=64, height=48, intrinsics=(50.0, 50.0, 32.0, 24.0), payload=payload)  # fmt: skip


def parts_of(whole: CameraFrame, part_bytes: int) -> list[CameraFrame]:
    chunks = split(whole.payload, part_bytes)
    return [replace(whole, payload=c, part=i, parts=len(chunks)) for i, c in enumerate(chunks)]


def test_split_covers_the_payload_in_order() -> None:
    data = bytes(range(256)) * 40
    parts = split(data, 1000)
    assert [len(p) for p in parts] == [1000] * 10 + [240]
    assert b"".join(parts) == data
    assert split(b"", 1000) == [b""]
    with pytest.raises(ValueError, match="part_bytes"):
        split(data, 0)


def test_pacer_spaces_sends_at_the_rate_with_no_saved_credit() -> None:
    pacer = Pacer(8e6)  # 1 byte per microsecond
    assert pacer.reserve(1000, 0) == 0  # first send goes at once
    assert pacer.reserve(1000, 0) == 1000_000  # the next waits for the first to drain: 1 ms
    assert pacer.reserve(1000, 500_000) == 1500_000
    # A quiet spell saves no credit: after 1 s idle, one send goes at once and the next waits again.
    assert pacer.reserve(1000, 1_000_000_000) == 0
    assert pacer.reserve(1000, 1_000_000_000) == 1000_000
    with pytest.raises(ValueError, match="rate_bps"):
        Pacer(0)


def test_a_paced_frame_spans_its_bytes_over_the_rate() -> None:
    pacer = Pacer(6.2e6)
    now = 0
    for part in split(bytes(44_000), 4096):
        now += pacer.reserve(len(part), now)
    assert now / MS == pytest.approx((44_000 - 3_040) * 8 / 6.2e6 * 1e3, rel=1e-6)  # the last part starts


def test_parts_round_trip_through_the_codec_and_bad_part_numbers_are_refused() -> None:
    parts = parts_of(frame(1, bytes(10_000)), 4096)
    assert [decode(encode(p)) for p in parts] == parts
    with pytest.raises(MessageError, match="part"):
        CameraFrame(**{**_fields(parts[0]), "part": 3, "parts": 3})
    body = encode(parts[0]).replace(b"\xa5parts\x03", b"\xa5parts\x00")
    with pytest.raises(DecodeError, match="parts"):
        decode(body)


def _fields(f: CameraFrame) -> dict[str, Any]:
    return {field.name: getattr(f, field.name) for field in fields(f)}


def test_assembler_joins_parts_in_any_order_and_passes_whole_frames_through() -> None:
    assembler = FrameAssembler()
    whole = frame(7, bytes(random.Random(1).randbytes(20_000)))
    parts = parts_of(whole, 4096)
    random.Random(2).shuffle(parts)
    out = [assembler.add(p) for p in parts]
    assert out[:-1] == [None] * (len(parts) - 1)
    assert out[-1] == whole
    assert len(assembler) == 0
    assert assembler.pending_bytes == 0
    single = frame(8, b"abc")
    assert assembler.add(single) is single


def test_a_frame_with_a_lost_part_is_given_up_when_a_newer_one_completes() -> None:
    assembler = FrameAssembler()
    lost = parts_of(frame(1, bytes(9000)), 4096)
    for p in lost[:-1]:
        assert assembler.add(p) is None
    other_kind = parts_of(frame(1, bytes(9000), kind="rgb"), 4096)
    assert assembler.add(other_kind[0]) is None
    newer = parts_of(frame(2, bytes(9000)), 4096)
    results = [assembler.add(p) for p in newer]
    assert results[-1] is not None
    assert results[-1].seq == 2
    assert assembler.incomplete == 1
    assert len(assembler) == 1  # the rgb frame 1 is another stream: still waiting for its parts


def test_duplicate_and_contradicting_parts_are_ignored() -> None:
    assembler = FrameAssembler()
    parts = parts_of(frame(3, bytes(9000)), 4096)
    assert assembler.add(parts[0]) is None
    assert assembler.add(parts[0]) is None  # duplicate
    liar = CameraFrame(**{**_fields(parts[1]), "stamp_ns": parts[1].stamp_ns + 1})
    assert assembler.add(liar) is None
    assert assembler.inconsistent == 1
    assert assembler.add(parts[1]) is None
    done = assembler.add(parts[2])
    assert done is not None
    assert len(done.payload) == 9000


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 40), st.integers(0, 7), st.integers(1, 200_000)), max_size=300))
def test_memory_stays_bounded_whatever_parts_arrive(arrivals: list[tuple[int, int, int]]) -> None:
    assembler = FrameAssembler(max_frames=8, max_bytes=300_000)
    for seq, part, size in arrivals:
        parts = 8
        assembler.add(CameraFrame(**{**_fields(frame(seq, b"")), "payload": bytes(size), "part": part,
                                     "parts": parts, "uav": f"uav{seq % 3}"}))  # fmt: skip
        assert len(assembler) <= 8
        assert assembler.pending_bytes <= 300_000
