"""The 5G core's QoS monitoring reports, forwarded to the drone whose flow they measure.

With `[qos.nef] qos_monitoring = true` the NEF reports the priority flow's uplink, downlink and
round-trip packet delays every `monitoring_period_s` (TS 23.501 clause 5.33.3). The network measures
them itself, whatever the edge answers, so the drone may read them as evidence of its link beside its
own latency windows (`[supervisor] network_aware`, docs/supervisor.md). The agent forwards each report
as it arrives, on the drone's `down/qos/monitoring` key (QosMonitoring), on the same priority as its
grants.
"""

from __future__ import annotations

from dynqos.common import keys
from dynqos.common.bus import Bus, Priority, Publisher
from dynqos.common.clock import Clock
from dynqos.common.keys import Downlink
from dynqos.common.messages import QosMonitoring
from dynqos.edge.operator.nef import Report


def _largest(delays: tuple[int, ...]) -> float | None:
    return float(max(delays)) if delays else None


class MonitoringForward:
    """One publisher per drone that has had a report (the drones this agent holds subscriptions for)."""

    def __init__(self, bus: Bus, clock: Clock, period_s: int) -> None:
        self.bus = bus
        self.clock = clock
        self.period_s = period_s
        self.forwarded = 0
        self._publishers: dict[str, Publisher] = {}
        self._seq = 0

    def __call__(self, uav: str, report: Report) -> None:
        publisher = self._publishers.get(uav)
        if publisher is None:
            key = keys.downlink(uav, Downlink.QOS_MONITORING)
            publisher = self._publishers[uav] = self.bus.publisher(key, Priority.INTERACTIVE_HIGH)
        self._seq += 1
        publisher.put(
            QosMonitoring(
                uav=uav,
                seq=self._seq,
                stamp_ns=self.clock.now_ns(),
                subscription_id=report.subscription_id[:64],
                uplink_ms=_largest(report.uplink_ms),
                downlink_ms=_largest(report.downlink_ms),
                round_trip_ms=_largest(report.round_trip_ms),
                period_s=self.period_s,
            )
        )
        self.forwarded += 1
