"""The last mission per drone, re-sent every period (edge/resend.py), on a fake clock."""

from __future__ import annotations

from dynqos.common.clock import NS_PER_S
from dynqos.common.messages import Message, MissionRequest
from dynqos.edge.resend import LatestMissions


class Recorder:
    def __init__(self) -> None:
        self.put_messages: list[Message] = []

    def put(self, message: Message) -> None:
        self.put_messages.append(message)


def _mission(uav: str, seq: int) -> MissionRequest:
    return MissionRequest(uav=uav, seq=seq, stamp_ns=0, waypoints_m=((0.0, 0.0, -2.0), (1.0, 0.0, -2.0)),
                          speed_mps=1.0, source="test")  # fmt: skip


def test_each_drones_latest_is_put_at_once_and_again_every_period() -> None:
    latest = LatestMissions(now_ns=0, period_s=1.0)
    one, two = Recorder(), Recorder()
    latest.send(_mission("uav1", 1), one, now_ns=0)
    latest.send(_mission("uav1", 2), one, now_ns=int(0.2 * NS_PER_S))  # replaces the first
    latest.send(_mission("uav2", 3), two, now_ns=int(0.4 * NS_PER_S))
    assert [m.seq for m in one.put_messages] == [1, 2]
    assert latest.publisher("uav1") is one
    assert latest.publisher("uav3") is None
    assert latest.resend_due(int(1.3 * NS_PER_S)) == 0  # a period after the last put, not the first
    assert latest.resend_due(int(1.4 * NS_PER_S)) == 2
    assert [m.seq for m in one.put_messages] == [1, 2, 2]
    assert [m.seq for m in two.put_messages] == [3, 3]
    assert latest.resend_due(int(2.3 * NS_PER_S)) == 0
    assert latest.resend_due(int(2.4 * NS_PER_S)) == 2


def test_nothing_sent_nothing_resent() -> None:
    assert LatestMissions(now_ns=0).resend_due(10 * NS_PER_S) == 0
