"""What the drone asks the network for, per path: a QosRequest to the agent of the site a path leads to.

The want follows the flow the path's state travels on (the drone's PFSM with one path, the path's own
with two, docs/supervisor.md): wanted while that flow is the priority flow, always with
`qos = "priority"`, never with `"default"`, and only in flight. qA flies its state on the priority flow,
but asks for it only when it came from a state that already wanted it: not after a watchdog in q1. A
changed want (or the risk it carries: an arbiter ranks by risk) goes at once, else the same want is
repeated every [qos] request_interval_s. Pure.
"""

from __future__ import annotations

from dataclasses import dataclass

from dynqos.common.clock import NS_PER_S
from dynqos.common.keys import Stream
from dynqos.common.messages import QosRequest
from dynqos.common.modes import Flow, SupervisorState
from dynqos.onboard.tick import Outgoing


@dataclass(frozen=True, slots=True)
class Need:
    """What one path's PFSM says about that path now."""

    path: str  # "" on a drone with one path
    flow: Flow  # the path's state flow
    state: SupervisorState | None  # None before the PFSM's first step
    risk: str
    p_lat: float | None


@dataclass
class _Asked:
    requested: bool | None = None  # the last want sent (None: none yet)
    risk: str = ""  # the risk level that request carried
    next_ns: int = 0


class QosAsking:
    """The requests for each of the drone's paths, numbered in one sequence."""

    def __init__(
        self, uav: str, paths: tuple[str, ...], period_ns: int, th_lat: float, start_ns: int
    ) -> None:
        self.uav = uav
        self.period_ns = period_ns
        self.th_lat = th_lat
        self.asked = {path: _Asked(next_ns=start_ns) for path in paths}
        self.seq = 0
        self._offered_at = (start_ns, 0)  # (when, camera bytes) at the last rate estimate
        self._offered_mbps = 0.0

    def requested(self, path: str | None = None) -> bool:
        """The last want sent on `path` was for priority (None: on any path)."""
        if path is not None:
            return bool(self.asked[path].requested)
        return any(a.requested for a in self.asked.values())

    def requests(self, now: int, qos: str, needs: list[Need], camera_bytes: int) -> list[Outgoing]:
        """The QosRequests due now, each on its own path (`qos`: [onboard] qos)."""
        out = []
        for need in needs:
            asked = self.asked[need.path]
            in_qa = need.state is SupervisorState.QA
            want = qos == "priority" or (need.flow is Flow.PRIORITY and (not in_qa or bool(asked.requested)))
            new_need = want and need.risk != asked.risk
            if want == asked.requested and not new_need and now < asked.next_ns:
                continue
            asked.requested, asked.risk, asked.next_ns = want, need.risk, now + self.period_ns
            self.seq += 1
            request = QosRequest(
                uav=self.uav,
                seq=self.seq,
                stamp_ns=now,
                want=want,
                risk=need.risk,
                latency_excess=0.0 if need.p_lat is None else need.p_lat - self.th_lat,
                offered_mbps=self._offered(now, camera_bytes),
            )
            out.append(Outgoing(Stream.QOS, need.flow, request, path=need.path))
        return out

    def _offered(self, now: int, camera_bytes: int) -> float:
        """The camera's bytes per second since the last estimate (over at least 0.2 s), in Mbit/s."""
        since, sent = self._offered_at
        if now - since >= NS_PER_S // 5:
            self._offered_mbps = (camera_bytes - sent) * 8e3 / (now - since)
            self._offered_at = (now, camera_bytes)
        return self._offered_mbps
