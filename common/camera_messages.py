"""The camera's messages: an encoded image (or one part of it), the edge's arrival ack, and the circles
the detector found. Registered and coded in common/messages.py, as every message is."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dynqos.common import fields as f
from dynqos.common.errors import MessageError
from dynqos.common.message_base import (
    CAMERA_ENCODINGS,
    CAMERA_KINDS,
    COMMON,
    MAX_DETECTIONS,
    MAX_FRAME_PARTS,
    MAX_PAYLOAD_BYTES,
    POSITION_LIMIT_M,
    Message,
)


@dataclass(frozen=True, slots=True, kw_only=True)
class CameraFrame(Message):
    """One encoded image, or one part of it; depth is 16-bit with `depth_unit_m` metres per count."""

    TYPE: ClassVar[str] = "CameraFrame"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "stamp_ns": f.integer(),
        "kind": f.choice(CAMERA_KINDS),
        "encoding": f.choice(CAMERA_ENCODINGS),
        "width": f.integer(1, 8192),
        "height": f.integer(1, 8192),
        "intrinsics": f.vector(4, 0.0, 1e6),
        "depth_unit_m": f.real(1e-6, 1.0),
        "payload": f.blob(MAX_PAYLOAD_BYTES),
        "part": f.integer(0, MAX_FRAME_PARTS - 1),
        "parts": f.integer(1, MAX_FRAME_PARTS),
    }

    stamp_ns: int
    kind: str
    encoding: str
    width: int
    height: int
    intrinsics: tuple[float, float, float, float]
    payload: bytes
    depth_unit_m: float = 0.001
    part: int = 0  # a paced frame travels in `parts` messages; the payloads in part order make the image
    parts: int = 1

    def _check(self) -> None:
        if self.intrinsics[0] <= 0.0 or self.intrinsics[1] <= 0.0:
            raise MessageError("intrinsics", "focal lengths fx and fy must be > 0")
        if self.part >= self.parts:
            raise MessageError("part", f"part {self.part} of a frame in {self.parts} parts")


@dataclass(frozen=True, slots=True, kw_only=True)
class CameraAck(Message):
    """Sent by the detector on arrival, before any processing, so the drone measures the network."""

    TYPE: ClassVar[str] = "CameraAck"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "frame_seq": f.integer(),
        "kind": f.choice(CAMERA_KINDS),
        "stamp_ns": f.integer(),
        "edge_hold_ns": f.integer(),
        "arrival_ns": f.integer(),
        "part_arrivals_us": f.sequence(f.integer(), 0, MAX_FRAME_PARTS),
    }

    frame_seq: int
    kind: str
    stamp_ns: int
    edge_hold_ns: int
    # When the image's first part arrived (the edge's clock; 0: not said), and each part's arrival that
    # many microseconds after it: the camera's delay-based rate controller reads them (docs/camera.md)
    arrival_ns: int = 0
    part_arrivals_us: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True, kw_only=True)
class Detections(Message):
    """Circles found in one RGB frame: pixel circles, and where depth allowed, 3-D centres and radii
    in the camera frame (metres); `centers_m[i]` is None where depth had no reading."""

    TYPE: ClassVar[str] = "Detections"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "frame_seq": f.integer(),
        "stamp_ns": f.integer(),
        "circles_px": f.sequence(f.vector(3, -1e5, 1e5), 0, MAX_DETECTIONS),
        "centers_m": f.sequence(
            f.optional(f.vector(4, -POSITION_LIMIT_M, POSITION_LIMIT_M)), 0, MAX_DETECTIONS
        ),
    }

    frame_seq: int
    stamp_ns: int
    circles_px: tuple[tuple[float, float, float], ...] = ()
    centers_m: tuple[tuple[float, float, float, float] | None, ...] = ()

    def _check(self) -> None:
        if len(self.centers_m) != len(self.circles_px):
            raise MessageError("centers_m", "must have one entry (or null) per circle in circles_px")
