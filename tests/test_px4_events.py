"""PX4's events read (onboard/px4_events.py): a packet checked by its CRC and unpacked, and PX4's own
sentence written from its catalogue, its arguments and enums in place; without a catalogue, the id."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest
from pymavlink.generator.mavcrc import x25crc

from dynqos.common.errors import ConfigError
from dynqos.onboard.px4_events import (
    EVENT_CRC_EXTRA,
    EVENT_FIELDS,
    LEVEL_DISABLED,
    Event,
    EventCatalogue,
    describe,
    parse_event,
)

# Two packets as PX4 main sent them on its offboard link right after boot, when asked to arm
HEADING = bytes.fromhex("fd1200001601019a0100f5decc018c0800000300000033fc007e00118e91")
SUMMARY = bytes.fromhex(
    "fd1e00001501019a0100e093a8018c0800000200000088000000120180000000003a0180003a01804a7c"
)
CATALOGUE = {
    "components": {
        "1": {
            "namespace": "px4",
            "enums": {
                "navigation_mode_group_t": {
                    "type": "uint32_t",
                    "is_bitfield": True,
                    "entries": {"1": {"name": "manual"}, "4": {"name": "posctl", "description": "Position"}},
                },
                "failsafe_action_t": {"type": "uint8_t", "entries": {"4": {"description": "Land"}}},
            },
            "event_groups": {
                "arming_check": {
                    "events": {
                        str(0xCCDEF5): {"message": "No heading reference", "arguments": []},
                        "7": {
                            "message": "{1}: <param>COM_X</param> {2:.1m} away, then {3}",
                            "arguments": [
                                {"type": "px4::navigation_mode_group_t"},
                                {"type": "float"},
                                {"type": "failsafe_action_t"},
                            ],
                        },
                    }
                }
            },
        }
    }
}


def packet(payload: bytes) -> bytes:
    """A MAVLink 2 EVENT packet around `payload`, with its CRC."""
    header = bytes([0xFD, len(payload), 0, 0, 9, 1, 1]) + (410).to_bytes(3, "little")
    crc = x25crc(header[1:] + payload)
    crc.accumulate(bytes([EVENT_CRC_EXTRA]))
    return header + payload + struct.pack("<H", crc.crc)


def test_a_real_px4_packet_is_unpacked_and_said_in_px4s_words() -> None:
    event = parse_event(HEADING)
    assert event is not None
    assert (event.id, event.level, event.sequence) == ((1 << 24) | 0xCCDEF5, 3, 3)  # 3: error
    assert describe(event, EventCatalogue(CATALOGUE)) == "No heading reference"
    summary = parse_event(SUMMARY)
    assert summary is not None
    assert summary.level == LEVEL_DISABLED  # a protocol event, for no log


def test_a_damaged_or_foreign_packet_is_not_an_event() -> None:
    assert parse_event(HEADING[:-1] + bytes([HEADING[-1] ^ 1])) is None  # its CRC fails
    assert parse_event(b"\xfe" + HEADING[1:]) is None  # MAVLink 1
    assert parse_event(HEADING[:8]) is None


def test_arguments_enums_units_and_tags_take_their_place_in_the_sentence() -> None:
    arguments = struct.pack("<IfB", 1 | 4, 2.25, 4)
    payload = EVENT_FIELDS.pack((1 << 24) | 7, 1000, 9, 0, 0, 0x44, arguments)
    event = parse_event(packet(payload.rstrip(b"\0")))  # MAVLink 2 trims the payload's trailing zeros
    assert event == Event((1 << 24) | 7, 1000, 9, 4, arguments.ljust(40, b"\0"))
    assert EventCatalogue(CATALOGUE).describe(event) == "manual, Position: COM_X 2.2 m away, then Land"


def test_without_a_catalogue_or_an_entry_the_event_is_said_by_its_id(tmp_path: Path) -> None:
    event = Event((1 << 24) | 99, 0, 0, 4, bytes(40))
    assert describe(event, None).startswith("PX4 event 0x01000063 ([onboard] px4_events")
    assert describe(event, EventCatalogue(CATALOGUE)) == "PX4 event 0x01000063 (not in the catalogue)"
    (tmp_path / "bad.json.xz").write_bytes(b"not xz")
    with pytest.raises(ConfigError, match="cannot read PX4's event catalogue"):
        EventCatalogue.load(tmp_path / "bad.json.xz")


def test_px4s_own_catalogue_reads_its_heading_refusal(px4_dir: Path) -> None:
    catalogue = EventCatalogue.load(px4_dir / "etc" / "extras" / "all_events.json.xz")
    event = parse_event(HEADING)
    assert event is not None
    assert catalogue.describe(event) == "No heading reference"
