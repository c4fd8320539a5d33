"""The drone's wall-clock offset to the edge, for the preflight (`dynqos onboard check`).

Nothing in the control loop needs the two clocks to agree (every latency is measured on one clock),
but the people reading a flight do: the drone's log, its MCAP and the edge's Prometheus series are lined
up by wall time, and TLS certificates are checked against it. So the preflight measures the offset and
fails it above MAX_OFFSET_MS.

How, with nothing added on the edge: the zenoh router stamps every sample it routes with its hybrid
logical clock, which runs on its host's wall clock (zenoh's `timestamping`, on for routers by default).
The drone puts a probe from one session and receives it on a second session, both through the router,
and takes, as NTP does, the router's stamp against the midpoint of its own send and receive times; of
several probes the one with the shortest round trip counts, and half that round trip bounds the error.
Pure: the probing itself is the preflight's (onboard/check.py).
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_OFFSET_MS = 50.0  # more than two control ticks: logs lined up by wall time would misplace events
PROBES = 5
PROBE_EVERY_S = 0.05


@dataclass(frozen=True, slots=True)
class Probe:
    sent_ns: int  # the drone's wall clock
    router_ns: int  # the router's stamp
    received_ns: int  # the drone's wall clock


@dataclass(frozen=True, slots=True)
class Offset:
    offset_ms: float  # router's clock minus the drone's
    error_ms: float  # at most this far off: half the round trip of the probe used


def estimate(probes: list[Probe]) -> Offset | None:
    """The offset from the probe with the shortest round trip (None: no probe)."""
    if not probes:
        return None
    best = min(probes, key=lambda p: p.received_ns - p.sent_ns)
    midpoint = (best.sent_ns + best.received_ns) / 2
    return Offset((best.router_ns - midpoint) / 1e6, (best.received_ns - best.sent_ns) / 2e6)
