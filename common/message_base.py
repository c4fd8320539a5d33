"""The base of every message between drone and edge: the schema version, the limits every field is
checked against, and construction that validates and normalises each field.

Split from common/messages.py (the registry and the codec) so that families of messages live in
modules of their own: the QoS agent's in common/qos_messages.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, TypeVar

from dynqos.common import fields as f
from dynqos.common.fastdecode import FastDecoder

SCHEMA_VERSION = 1
MAX_MESSAGE_BYTES = 24 * 1024 * 1024
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
MAX_HORIZON = 64
MAX_REFERENCE_SAMPLES = 400
MAX_DETECTIONS = 64
MAX_FRAME_PARTS = 4096
MAX_STATUS_SAMPLES = 256
MAX_MISSION_WAYPOINTS = 256
FC_TEXT_MAX = 160  # a STATUSTEXT is at most 50 characters; a PX4 event, described, somewhat more

POSITION_LIMIT_M = 1e5
VELOCITY_LIMIT_MPS = 1e3
ACCEL_LIMIT_MPS2 = 100.0
LATENCY_LIMIT_MS = 1e7
# What a 5G modem reports (3GPP TS 38.133's reporting ranges): SS-RSRP -156..-31 dBm, SS-SINR -23..40 dB
RSRP_RANGE_DBM = (-156.0, -31.0)
SINR_RANGE_DB = (-23.0, 40.0)

CAMERA_KINDS = ("rgb", "depth")
RISK_LEVELS = ("HR", "MR", "LR", "NA")
CAMERA_ENCODINGS = ("jpeg", "png", "png16", "zstd16", "raw8", "raw16")

POSITION = f.vector(3, -POSITION_LIMIT_M, POSITION_LIMIT_M)
VELOCITY = f.vector(3, -VELOCITY_LIMIT_MPS, VELOCITY_LIMIT_MPS)
ANGLE = f.real(-100.0, 100.0)
PROBABILITY = f.real(0.0, 1.0)
LATENCY_MS = f.real(0.0, LATENCY_LIMIT_MS)

M = TypeVar("M", bound="Message")


class Construction:
    """How a message checks its fields when constructed: in C by the decoder that common/messages.py
    installs once every type is known (`fast`), unless a test turns it off (`enabled`) to compare with
    the checks alone, which name the field."""

    fast: FastDecoder | None = None
    enabled: bool = True


CONSTRUCTION = Construction()


@dataclass(frozen=True, slots=True, kw_only=True)
class Message:
    """Base of all messages: validates and normalises every field when constructed."""

    TYPE: ClassVar[str] = ""
    SCHEMA: ClassVar[dict[str, f.Validator]] = {}

    uav: str
    seq: int

    def __post_init__(self) -> None:
        fast = CONSTRUCTION.fast
        if not (CONSTRUCTION.enabled and fast is not None and fast.normalise(self)):  # in C; else each check
            for name, check in self.SCHEMA.items():
                object.__setattr__(self, name, check(name, getattr(self, name)))
        self._check()

    def _check(self) -> None:
        """Cross-field rules; override where a message has them."""


COMMON: dict[str, f.Validator] = {"uav": f.uav_id, "seq": f.integer()}
