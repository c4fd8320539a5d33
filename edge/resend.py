"""The last mission sent to each drone, put once more every period: a planner replica that starts, or
takes a drone over, after a mission went out flies it too (a planner keeps the newest mission it has
seen per drone, by seq, so a repeat changes nothing for one that has it). Whoever sends missions from
outside the planner keeps one of these: the ROS 2 bridge and the fleet planner."""

from __future__ import annotations

from dynqos.common.bus import Publisher
from dynqos.common.clock import NS_PER_S
from dynqos.common.messages import MissionRequest

RESEND_S = 1.0


class LatestMissions:
    def __init__(self, now_ns: int, period_s: float = RESEND_S) -> None:
        self._period_ns = int(period_s * NS_PER_S)
        self._sent: dict[str, tuple[MissionRequest, Publisher]] = {}
        self._resent_ns = now_ns

    def send(self, request: MissionRequest, publisher: Publisher, now_ns: int) -> None:
        """Put `request` now, and keep it (with its publisher) as its drone's latest."""
        publisher.put(request)
        self._sent[request.uav] = (request, publisher)
        self._resent_ns = now_ns

    def publisher(self, uav: str) -> Publisher | None:
        """The publisher the drone's last mission went out on, if one did."""
        sent = self._sent.get(uav)
        return None if sent is None else sent[1]

    def resend_due(self, now_ns: int) -> int:
        """Every drone's latest once more when a period has passed since the last put; how many."""
        if now_ns - self._resent_ns < self._period_ns:
            return 0
        self._resent_ns = now_ns
        for request, publisher in self._sent.values():
            publisher.put(request)
        return len(self._sent)
