"""Everything the QoS agent keeps of one drone, in one record so that forgetting a drone is one step
(parallel per-drone maps would each need the same pop, and one missed is a leak)."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from dynqos.common.bus import Publisher
from dynqos.edge.qos.arbiter import Need
from dynqos.edge.qos.grants import DroneGrant


@dataclass(eq=False)
class DroneRecord:
    """Everything the agent keeps of one drone, so that forgetting it is one step: its grant rules, the
    event that wakes its task, the task, its publishers, its latest need and the arbiter's refusal."""

    grant: DroneGrant
    publisher: Publisher  # its grants
    decisions: Publisher | None = None  # the arbiter's decisions about it (policy "arbiter")
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None
    need: Need = field(default_factory=Need)  # from its latest request
    refusal: str = ""  # why the arbiter does not admit it ("": no reason said)

    def close(self) -> None:
        self.publisher.close()
        if self.decisions is not None:
            self.decisions.close()
