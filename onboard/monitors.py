"""What the drone measures of its latency: the camera's from CameraAcks (ack arrival - frame stamp - edge
hold, on the drone's clock), and the samples of both latencies kept for the next SupervisorStatus. Pure."""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Iterable

from dynqos.common.message_base import LATENCY_LIMIT_MS, MAX_STATUS_SAMPLES
from dynqos.common.messages import CameraAck, QosMonitoring


class CameraLatencyMonitor:
    def __init__(self, max_outstanding: int = 256) -> None:
        self._outstanding: OrderedDict[tuple[int, str], int] = OrderedDict()
        self._max = max_outstanding
        self._new: list[float] = []
        self.acked = 0
        self.unknown = 0
        self.last_ms: float | None = None

    def frame_sent(self, seq: int, kind: str, stamp_ns: int) -> None:
        self._outstanding[(seq, kind)] = stamp_ns
        while len(self._outstanding) > self._max:
            self._outstanding.popitem(last=False)

    def on_ack(self, ack: CameraAck, arrival_ns: int) -> float | None:
        stamp = self._outstanding.pop((ack.frame_seq, ack.kind), None)
        if stamp is None or stamp != ack.stamp_ns:
            self.unknown += 1
            return None
        # Frames sent before this one that were never acked are lost: stop waiting for them.
        for key in [k for k, s in self._outstanding.items() if s < stamp]:
            del self._outstanding[key]
        latency_ms = (arrival_ns - stamp - ack.edge_hold_ns) / 1e6
        self.acked += 1
        if latency_ms >= 0:
            self._new.append(latency_ms)
            self.last_ms = latency_ms
        return latency_ms

    def take_new(self) -> list[float]:
        out, self._new = self._new, []
        return out

    def oldest_outstanding_ms(self, now_ns: int) -> float | None:
        if not self._outstanding:
            return None
        return (now_ns - next(iter(self._outstanding.values()))) / 1e6


class LatencySamples:
    """The latency samples measured since the last SupervisorStatus (bounded: the newest are kept)."""

    def __init__(self) -> None:
        self._cams: deque[float] = deque(maxlen=MAX_STATUS_SAMPLES)
        self._rtts: deque[float] = deque(maxlen=MAX_STATUS_SAMPLES)

    def extend(self, cams: Iterable[float], rtts: Iterable[float]) -> None:
        self._cams.extend(c for c in cams if 0 <= c <= LATENCY_LIMIT_MS)
        self._rtts.extend(r for r in rtts if 0 <= r <= LATENCY_LIMIT_MS)

    def take(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        out = (tuple(self._cams), tuple(self._rtts))
        self._cams.clear()
        self._rtts.clear()
        return out


class NetworkDelays:
    """The 5G core's latest report of the priority flow's round-trip delay (QosMonitoring, forwarded by
    the QoS agent), fresh for two of its reporting periods after it arrived on the drone's clock."""

    def __init__(self) -> None:
        self.reports = 0
        self._round_trip_ms: float | None = None
        self._fresh_until_ns = 0

    def offer(self, report: QosMonitoring, arrival_ns: int) -> None:
        self.reports += 1
        self._round_trip_ms = report.round_trip_ms
        self._fresh_until_ns = arrival_ns + 2 * report.period_s * 1_000_000_000

    def round_trip_ms(self, now_ns: int) -> float | None:
        return self._round_trip_ms if now_ns <= self._fresh_until_ns else None
