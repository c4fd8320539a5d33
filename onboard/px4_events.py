"""PX4's events, read: PX4 reports its arming checks, failsafes and most of what it has to say as MAVLink
EVENT messages (id 410; a numeric id and up to 40 bytes of arguments), not as STATUSTEXT. pymavlink's
dialects do not know EVENT yet, so the link hands over the raw packet; this module checks it (its CRC,
with EVENT's CRC extra), unpacks it, and writes it as PX4's own sentence from PX4's event catalogue
(`all_events.json.xz`, which every PX4 build makes: `build/<target>/events/` in PX4's tree, `etc/extras/`
in a packaged SITL).

Pure: bytes and a catalogue in, a level and a sentence out (tests/test_px4_events.py). Without a
catalogue an event is still said, by its id, so a refusal is never silent.
"""

from __future__ import annotations

import json
import lzma
import re
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink.generator.mavcrc import x25crc

from dynqos.common.errors import ConfigError

EVENT_ID = 410
UNKNOWN_EVENT = f"UNKNOWN_{EVENT_ID}"  # how pymavlink names a message its dialect does not know
EVENT_CRC_EXTRA = 160
EVENT_FIELDS = struct.Struct("<IIHBBB40s")  # id, time_boot_ms, sequence, dest comp, dest sys, levels, args
HEADER_BYTES = 10  # MAVLink 2: STX, len, incompat, compat, seq, sysid, compid, msgid (3)
LEVEL_DISABLED = 8  # a protocol event (the arming checks' summary) meant for no log
BASE_TYPES = {
    "uint8_t": "B",
    "int8_t": "b",
    "uint16_t": "H",
    "int16_t": "h",
    "uint32_t": "I",
    "int32_t": "i",
    "uint64_t": "Q",
    "int64_t": "q",
    "float": "f",
}
UNITS = {"m": " m", "m_v": " m", "m/s": " m/s", "C": " degC"}
PLACEHOLDER = re.compile(r"\{(\d+)(?::?\.?(\d*)([^}]*))?\}")
TAG = re.compile(r"</?[a-z]+[^>]*>")


@dataclass(frozen=True, slots=True)
class Event:
    id: int
    time_boot_ms: int
    sequence: int
    level: int  # the external log level: MAV_SEVERITY's 0 (emergency) .. 7 (debug); 8 and up: none
    arguments: bytes


def parse_event(packet: bytes) -> Event | None:
    """An EVENT from a whole MAVLink 2 packet (signed or not), or None if it is not one or fails its CRC."""
    if len(packet) < HEADER_BYTES + 2 or packet[0] != 0xFD:
        return None
    length = packet[1]
    if len(packet) < HEADER_BYTES + length + 2 or int.from_bytes(packet[7:10], "little") != EVENT_ID:
        return None
    crc = x25crc(packet[1 : HEADER_BYTES + length])
    crc.accumulate(bytes([EVENT_CRC_EXTRA]))
    if crc.crc != int.from_bytes(packet[HEADER_BYTES + length : HEADER_BYTES + length + 2], "little"):
        return None
    payload = packet[HEADER_BYTES : HEADER_BYTES + length].ljust(EVENT_FIELDS.size, b"\0")  # zeros trimmed
    event_id, time_ms, sequence, _comp, _sys, levels, arguments = EVENT_FIELDS.unpack(payload)
    return Event(event_id, time_ms, sequence, levels & 0x0F, arguments)


class EventCatalogue:
    """PX4's events by id, with each component's enums, from `all_events.json` (or `.json.xz`)."""

    def __init__(self, metadata: Mapping[str, Any]) -> None:
        self._events: dict[int, dict[str, Any]] = {}
        self._enums: dict[str, dict[str, Any]] = {}
        for component, body in metadata.get("components", {}).items():
            namespace = body.get("namespace", "")
            for name, enum in body.get("enums", {}).items():
                self._enums[f"{namespace}::{name}"] = enum
                self._enums.setdefault(name, enum)
            for group in body.get("event_groups", {}).values():
                for sub_id, event in group.get("events", {}).items():
                    self._events[(int(component) << 24) | int(sub_id)] = event

    @classmethod
    def load(cls, path: str | Path) -> EventCatalogue:
        source = Path(path)
        try:
            raw = source.read_bytes()
            text = lzma.decompress(raw) if source.suffix == ".xz" else raw
            return cls(json.loads(text))
        except (OSError, lzma.LZMAError, ValueError) as exc:
            raise ConfigError(
                "onboard.px4_events", f"cannot read PX4's event catalogue {source}: {exc}"
            ) from None

    def describe(self, event: Event) -> str:
        """PX4's sentence for `event`, its arguments in place (a tag such as <param> keeps its text)."""
        known = self._events.get(event.id)
        if known is None:
            return f"PX4 event {event.id:#010x} (not in the catalogue)"
        values = self._arguments(known.get("arguments", []), event.arguments)
        return TAG.sub("", PLACEHOLDER.sub(lambda m: _placed(values, m), known.get("message", "")))

    def _arguments(self, declared: list[dict[str, Any]], data: bytes) -> list[str]:
        values, offset = [], 0
        for argument in declared:
            kind = argument.get("type", "")
            enum = self._enums.get(kind)
            code = BASE_TYPES.get(enum["type"] if enum else kind)
            if code is None or offset + struct.calcsize(code) > len(data):
                break
            (value,) = struct.unpack_from("<" + code, data, offset)
            offset += struct.calcsize(code)
            values.append(_enum_text(enum, value) if enum else value)
        return values


def _enum_text(enum: Mapping[str, Any], value: int) -> str:
    entries = enum.get("entries", {})
    if not enum.get("is_bitfield"):
        entry = entries.get(str(value))
        return str(entry.get("description") or entry.get("name")) if entry else str(value)
    names = [str(e.get("description") or e.get("name")) for bit, e in entries.items() if value & int(bit)]
    return ", ".join(names) or "none"


def _placed(values: list[Any], match: re.Match[str]) -> str:
    index = int(match.group(1)) - 1
    if not 0 <= index < len(values):
        return match.group(0)
    value, digits, unit = values[index], match.group(2), (match.group(3) or "").strip()
    text = f"{value:.{int(digits)}f}" if digits and isinstance(value, float) else str(value)
    return text + UNITS.get(unit, "")


def describe(event: Event, catalogue: EventCatalogue | None) -> str:
    """What the daemon logs: PX4's sentence, or the event's id where there is no catalogue."""
    if catalogue is None:
        return f"PX4 event {event.id:#010x} ([onboard] px4_events names PX4's catalogue to read it)"
    return catalogue.describe(event)
