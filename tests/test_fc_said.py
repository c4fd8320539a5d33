"""What the flight controller says reaches the drone's status and the flight's summary (docs/px4.md): a
real STATUSTEXT read by the MAVLink link, kept with its severity and arrival; each text once in the
summary, when it first came. The core's side is in tests/test_onboard_core.py."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import common as mavlink

from dynqos.common.clock import FakeClock
from dynqos.common.errors import MessageError
from dynqos.common.messages import FC_TEXT_MAX, decode, encode
from dynqos.onboard.fc import FcSaid
from dynqos.onboard.fclink import FcLink
from dynqos.reports.summary import FC_SAID_KEPT, fc_said
from tests.conftest import free_tcp_port
from tests.statuses import status_saying as _status


def test_a_statustext_becomes_what_the_fc_said_with_its_severity_and_arrival() -> None:
    clock = FakeClock(5_000_000_000)
    link = FcLink(f"udpin:127.0.0.1:{free_tcp_port()}", clock=clock)
    try:
        assert link.said is None
        link._said(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_CRITICAL, b"Preflight Fail: GPS"))
        assert link.said == FcSaid("Preflight Fail: GPS", mavlink.MAV_SEVERITY_CRITICAL, 5_000_000_000)
        clock.advance_ns(1_000_000)
        link._said(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, b"Takeoff detected"))
        assert link.said == FcSaid("Takeoff detected", mavlink.MAV_SEVERITY_INFO, 5_001_000_000)
        link._said(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, b"   "))  # nothing said
        assert link.said.text == "Takeoff detected"
        assert link.texts == ["Preflight Fail: GPS", "Takeoff detected"]
    finally:
        link.close()


def test_the_summary_lists_each_text_once_from_when_it_first_came() -> None:
    t0 = 10_000_000_000
    statuses = [
        _status(t0 - 2_000_000_000, "Armed by external command", 6),
        _status(t0 - 1_900_000_000, "Armed by external command", 6),  # still riding in the status
        _status(t0, "", None),
        _status(t0 + 1_500_000_000, "Failsafe: offboard control lost", 4),
    ]
    assert fc_said(statuses, t0) == [
        {"t_s": -2.0, "severity": 6, "text": "Armed by external command"},
        {"t_s": 1.5, "severity": 4, "text": "Failsafe: offboard control lost"},
    ]
    many = [_status(t0 + i, f"text {i}", 6) for i in range(FC_SAID_KEPT + 5)]
    assert len(fc_said(many, t0)) == FC_SAID_KEPT  # bounded


def test_the_status_carries_the_longest_text_and_refuses_a_longer_one_or_a_severity_out_of_range() -> None:
    longest = _status(1, "x" * FC_TEXT_MAX, 7)
    assert decode(encode(longest)) == longest
    for text, severity in (("x" * (FC_TEXT_MAX + 1), 6), ("ok", 8), ("ok", -1)):
        with pytest.raises(MessageError):
            _status(1, text, severity)
