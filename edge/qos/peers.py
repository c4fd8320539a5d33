"""The I/O shell of edge/qos/leadership.py: this agent's tokens, and the other agents' as zenoh reports
them, handed to the agent's event loop.

zenoh reports token changes on its own threads; they wait, bounded, in a map that the loop drains (a
flood beyond the bound is refused and counted), and the loop is woken once per batch.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from dynqos.common import keys
from dynqos.common.bus import Bus, Token
from dynqos.common.clock import NS_PER_S, Clock, to_ns
from dynqos.common.queues import PendingChanges
from dynqos.edge.qos.leadership import Leadership

log = logging.getLogger(__name__)

MAX_PENDING_CHANGES = 1024
QUERY_TIMEOUT_S = 2.0  # the live set asked for at start


class AgentPeers:
    def __init__(self, bus: Bus, group: str, leadership: Leadership, loop: asyncio.AbstractEventLoop) -> None:
        self.bus = bus
        self.group = group
        self.leadership = leadership
        self.changed = asyncio.Event()  # set (on the loop) when changes wait in `_pending`
        self._refusal_logged = False
        self._loop = loop
        self._pending: PendingChanges[tuple[str, str]] = PendingChanges(MAX_PENDING_CHANGES)  # (kind, agent)
        self._active_token: Token | None = None
        members, actives = keys.replicas_of("qos", group), keys.qos_actives(group)
        bus.watch_tokens(members, lambda key, alive: self._on_token("member", key, alive))
        bus.watch_tokens(actives, lambda key, alive: self._on_token("active", key, alive))
        self._member_token = bus.declare_token(keys.replica_token("qos", group, leadership.me))

    def query(self) -> None:
        """The live set as the router knows it now (blocking: run it off the loop)."""
        for kind, key_expr in (("member", keys.replicas_of("qos", self.group)),
                               ("active", keys.qos_actives(self.group))):  # fmt: skip
            for key in self.bus.alive_tokens(key_expr, timeout_s=QUERY_TIMEOUT_S):
                self._on_token(kind, key, True)

    def _on_token(self, kind: str, key: str, alive: bool) -> None:
        """zenoh's thread: note the change; the loop applies it."""
        agent = keys.replica_of_token(key)
        if self._pending.offer((kind, agent), alive):
            with contextlib.suppress(RuntimeError):  # the loop has closed: the agent is stopping
                self._loop.call_soon_threadsafe(self.changed.set)

    @property
    def refused(self) -> int:
        """Changes beyond MAX_PENDING_CHANGES."""
        return self._pending.refused

    def apply(self) -> None:
        """The loop: the changes since the last call, into the leadership, each logged."""
        self.changed.clear()
        changes = self._pending.take()
        lead = self.leadership
        for (kind, agent), alive in changes.items():
            seen = lead.member(agent, alive) if kind == "member" else lead.active(agent, alive)
            if seen:
                what = "agent" if kind == "member" else "active agent"
                log.info("qos agent %s: %s %s %s", lead.me, what, agent, "joined" if alive else "left")
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
            log.warning("qos agent %s: no standby took over within %.0f s: deleting the sessions",
                        lead.me, timeout_s)  # fmt: skip
            return False
        log.info(
            "qos agent %s: stopping; %s took the sessions over", lead.me, ", ".join(sorted(lead.actives))
        )
        return True

    def close(self) -> None:
        self.release()
        self._member_token.close()
