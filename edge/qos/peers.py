"""The I/O shell of edge/qos/leadership.py: this agent's tokens, and the other agents' as zenoh reports
them, handed to the agent's event loop.

The tokens are watched by edge/presence.py, which wakes the loop once per batch of changes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from dynqos.common import keys
from dynqos.common.bus import Bus, Token
from dynqos.common.clock import NS_PER_S, Clock, to_ns
from dynqos.common.lifecycle import waker
from dynqos.edge.presence import Presence, Watch
from dynqos.edge.qos.leadership import Leadership

log = logging.getLogger(__name__)

MAX_PENDING_CHANGES = 1024
QUERY_TIMEOUT_S = 2.0  # the live set asked for at start


class AgentPeers:
    def __init__(self, bus: Bus, group: str, leadership: Leadership, loop: asyncio.AbstractEventLoop) -> None:
        self.bus = bus
        self.group = group
        self.leadership = leadership
        self.changed = asyncio.Event()  # set (on the loop) when changes wait in the presence
        self._refusal_logged = False
        self._active_token: Token | None = None
        # names are the Leadership's to validate and cap (its `refused`)
        self.presence = Presence(
            bus,
            f"qos agent {leadership.me}",
            [
                Watch("member", keys.replicas_of("qos", group), keys.replica_of_token),
                Watch("active", keys.qos_actives(group), keys.replica_of_token),
            ],
            pending_limit=MAX_PENDING_CHANGES,
            wake=waker(loop, self.changed.set),  # zenoh's thread: changes wait; the loop applies them
        )
        self._member_token = bus.declare_token(keys.replica_token("qos", group, leadership.me))

    def query(self) -> None:
        """The live set as the router knows it now (blocking: run it off the loop)."""
        self.presence.query(QUERY_TIMEOUT_S)

    @property
    def refused(self) -> int:
        """Changes beyond MAX_PENDING_CHANGES."""
        return self.presence.refused

    def apply(self) -> None:
        """The loop: the changes since the last call, into the leadership, each logged."""
        self.changed.clear()
        lead = self.leadership
        for seen in self.presence.take():
            member = seen.kind == "member"
            if lead.member(seen.name, seen.alive) if member else lead.active(seen.name, seen.alive):
                what = "agent" if member else "active agent"
                log.info(
                    "qos agent %s: %s %s %s", lead.me, what, seen.name, "joined" if seen.alive else "left"
                )
        refused = lead.refused + self.refused
        if refused and not self._refusal_logged:  # a flood is logged once; the health line counts it
            log.warning("qos agent %s: agent tokens refused (invalid names or too many)", lead.me)
            self._refusal_logged = True

    def claim(self) -> None:
        """Hold the active token (before any session is touched, so that peers see it first)."""
        if self._active_token is None:
            self._active_token = self.bus.declare_token(keys.qos_active(self.group, self.leadership.me))

    def release(self) -> None:
        if self._active_token is not None:
            self._active_token.close()
            self._active_token = None

    async def hand_over(self, clock: Clock, timeout_s: float) -> bool:
        """This active agent is stopping: with a standby alive, drop the active token and wait for the
        standby's (it adopts the sessions). No standby, or none that takes over in time (it is
        stopping too): False, and the caller deletes the sessions."""
        lead = self.leadership
        self.apply()
        if len(lead.members) <= 1:
            return False
        self.release()
        deadline = clock.now_ns() + to_ns(timeout_s)
        while not lead.actives and clock.now_ns() < deadline:
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(self.changed.wait(), (deadline - clock.now_ns()) / NS_PER_S)
            self.apply()
        if not lead.actives:
            log.warning(
                "qos agent %s: no standby took over within %.0f s: deleting the sessions", lead.me, timeout_s
            )
            return False
        log.info(
            "qos agent %s: stopping; %s took the sessions over", lead.me, ", ".join(sorted(lead.actives))
        )
        return True

    def close(self) -> None:
        self.release()
        self._member_token.close()
