"""Which QoS agent holds the operator sessions: one is active, the others stand by. Pure.

Two agents that both held sessions would each create, extend and delete them for the same drones: the
operator would see conflicts (409) and, worse, one agent deleting what the other extends. So at most
one agent is active at a time, chosen over the same zenoh liveliness tokens the MPC and planner replicas
use (edge/replicas.py): every agent holds a member token, and the active one holds an `active` token
too. Liveliness rather than a Kubernetes Lease because it works wherever dynqos runs (one laptop,
systemd, Kubernetes), needs no API-server permission, and is told at once when a process dies (its
session closes and the router withdraws its tokens), where a Lease is taken over only when it expires
(15 s by default). A hung agent keeps its tokens until its zenoh session's lease runs out (`[qos]
session_lease_s`, 2 s); that is the takeover time for a hang (docs/qos.md).

The rules, applied whenever the tokens change:
- an active agent stays active while it lives (a new agent never displaces it, so sessions do not move
  for nothing);
- with no active agent, the first-ranked live agent (rendezvous order, as the replicas rank) becomes
  active; the others wait, so that two standbys do not both take over;
- two active agents (both took over at once, or a partition healed) are settled by rank: the other
  one steps down and hands its drones to the first-ranked, which found the sessions already (no
  duplicate create: it adopts what the operator holds for each drone, edge/qos/agent.py).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from dynqos.common.keys import check_replica_id, valid_replica_id
from dynqos.edge.replicas import MAX_REPLICAS, ranked

RANK_KEY = "qos-active"  # what the agents are ranked for (one choice for the whole group)


class AgentRole(str, enum.Enum):
    ACTIVE = "active"  # holds the operator sessions and tells the drones their grants
    STANDBY = "standby"  # follows the drones' requests, calls nothing, tells nothing


class Guard(enum.Enum):
    """What moves an agent from one role to the other, read from the tokens and the clock."""

    TAKE_OVER = "no agent holds an active token, the settle time is over, and this one ranks first"
    STEP_DOWN = "another agent holds an active token too and ranks first"


# Every change of role; nothing else changes one (an agent that lives stays active). An enum and a table
# as the drone's take-off has (onboard/takeoff.py): two rows do not need a library.
TRANSITIONS: dict[tuple[AgentRole, Guard], AgentRole] = {
    (AgentRole.STANDBY, Guard.TAKE_OVER): AgentRole.ACTIVE,
    (AgentRole.ACTIVE, Guard.STEP_DOWN): AgentRole.STANDBY,
}


@dataclass(frozen=True, slots=True)
class Transition:
    role: AgentRole
    reason: str


class Leadership:
    def __init__(self, me: str, *, now_ns: int, settle_ns: int) -> None:
        """`settle_ns`: how long after start an agent waits before it takes over, so that peers that
        start with it have declared their tokens (only the first-ranked of them then takes over)."""
        check_replica_id(me, "agent id")
        self.me = me
        self.role = AgentRole.STANDBY
        self.members: set[str] = {me}
        self.actives: set[str] = set()  # the others that hold an active token
        self.refused = 0  # tokens with an invalid name or beyond MAX_REPLICAS
        self.takeovers = 0
        self._settled_ns = now_ns + settle_ns

    def member(self, agent: str, alive: bool) -> bool:
        """A member token came or went; True when the live set changed."""
        return self._change(self.members, agent, alive)

    def active(self, agent: str, alive: bool) -> bool:
        """An active token came or went; True when the set changed (our own is not counted)."""
        return self._change(self.actives, agent, alive)

    def _change(self, group: set[str], agent: str, alive: bool) -> bool:
        if agent == self.me:
            return False
        if not alive:
            if agent in group:
                group.discard(agent)
                return True
            return False
        if agent in group:
            return False
        if not valid_replica_id(agent) or len(group) >= MAX_REPLICAS:
            self.refused += 1
            return False
        group.add(agent)
        return True

    def decide(self, now_ns: int) -> Transition | None:
        """The role this agent should take now, when it changes."""
        guard, reason = self._guard(now_ns)
        if guard is None:
            return None
        self.role = TRANSITIONS[(self.role, guard)]
        if self.role is AgentRole.ACTIVE:
            self.takeovers += 1
        return Transition(self.role, reason)

    def _guard(self, now_ns: int) -> tuple[Guard | None, str]:
        if self.role is AgentRole.ACTIVE:
            first = ranked(RANK_KEY, self.actives | {self.me})[0]
            if first != self.me:
                return Guard.STEP_DOWN, f"{first} is active too and ranks first"
            return None, ""
        if self.actives or now_ns < self._settled_ns or ranked(RANK_KEY, self.members)[0] != self.me:
            return None, ""
        peers = len(self.members) - 1
        return Guard.TAKE_OVER, f"no agent is active ({peers} other agent(s) standing by)"

    def next_deadline_ns(self, now_ns: int) -> int | None:
        """When `decide` may change its answer without a token changing (the end of the settle time)."""
        return self._settled_ns if now_ns < self._settled_ns else None

    @property
    def is_active(self) -> bool:
        return self.role is AgentRole.ACTIVE
