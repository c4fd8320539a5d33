"""The control loop's uplink: what a tick publishes goes on the wire from a thread per flow.

The state and the QoS requests are published with zenoh's BLOCK congestion control, so that a link
that backs up for a moment delays them instead of losing them. But a put with BLOCK waits as long as
the link is backed up, up to zenoh's `wait_before_close` (5 s) when coverage is lost; on the tick
thread that wait stopped the setpoints to the flight controller, and the FC left offboard mode while
the fallback controller that should have flown it waited behind the put. Here the tick only appends
to a bounded queue per flow and never waits on the network; a sender thread per flow does the put,
so a default flow that backs up holds neither the tick nor the priority flow. When a flow stays
blocked, its queue keeps the newest messages (a state's use is its freshness) and counts the ones it
let go.
"""

from __future__ import annotations

import logging
import threading

from dynqos.common.bus import Publisher
from dynqos.common.messages import Message
from dynqos.common.modes import Flow
from dynqos.common.queues import BoundedQueue

log = logging.getLogger(__name__)

# Per flow: at the 50 Hz tick, a state and a status per tick give about 0.3 s of messages. Older ones
# are of no use to the MPC when the link comes back, and the bound keeps a long outage's memory flat.
QUEUE_DEPTH = 32
IDLE_WAIT_S = 0.1  # how often an idle sender looks at the stop flag


class Uplink:
    """A bounded queue and a sender thread per flow; `put` never blocks."""

    def __init__(self, stop: threading.Event, depth: int = QUEUE_DEPTH) -> None:
        self.stop = stop
        self.queues: dict[Flow, BoundedQueue[tuple[Publisher, Message]]] = {
            flow: BoundedQueue(depth) for flow in Flow
        }
        self._threads: list[threading.Thread] = []
        self._reported: dict[Flow, int] = dict.fromkeys(Flow, 0)

    def put(self, flow: Flow, publisher: Publisher, message: Message) -> None:
        """Queue `message` for `publisher` on `flow`'s sender (the oldest queued one goes if full)."""
        self.queues[flow].put((publisher, message))

    def start(self) -> None:
        for flow in Flow:
            name = f"uplink-{flow.value}"
            thread = threading.Thread(target=self._send, args=(flow,), name=name, daemon=True)
            thread.start()
            self._threads.append(thread)

    def join(self, timeout_s: float) -> None:
        """Wait for the senders to end (after `stop`); one blocked in a put is left to zenoh's close."""
        for thread in self._threads:
            thread.join(timeout=timeout_s)

    @property
    def dropped(self) -> int:
        """Messages let go because their flow's queue was full: the link was blocked for that long."""
        return sum(queue.dropped for queue in self.queues.values())

    def pending(self) -> int:
        return sum(len(queue) for queue in self.queues.values())

    def report(self) -> None:
        """Log once per batch of newly dropped messages, per flow (called from the tick's health line)."""
        for flow, queue in self.queues.items():
            new = queue.dropped - self._reported[flow]
            if new > 0:
                self._reported[flow] = queue.dropped
                log.warning(
                    "onboard: the %s flow is blocked: %d queued messages let go (the newest are kept)",
                    flow.value,
                    new,
                )

    def _send(self, flow: Flow) -> None:
        queue = self.queues[flow]
        while not self.stop.is_set():
            item = queue.get(timeout_s=IDLE_WAIT_S)
            if item is None:
                continue
            publisher, message = item
            try:
                publisher.put(message)
            except Exception as err:  # a closed session at shutdown; zenoh raises its own ZError
                if not self.stop.is_set():
                    log.error("onboard: %s uplink put on %s failed: %s", flow.value, publisher.key, err)
