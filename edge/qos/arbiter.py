"""Who gets priority when not every drone can: the QoS agent's arbiter, as pure logic with time passed in.

The paper ends on its own limit: if every user takes elevated priority, priority means nothing. With
`[qos] policy = "arbiter"` the agent grants priority within a budget (at most `max_grants` drones, and
at most `max_share` of the cell's uplink by what the holders offer) and by need, so the drones in
danger keep their real-time loop and the others degrade through the supervisor's rate adaptation
(docs/fleet.md). The rules, each in one place:

- need is risk first (HR over MR over LR; NA counts as MR, as in the supervisor), then how far the
  drone's latency is over its supervisor's threshold, compared in steps so that noise does not reorder;
- a holder is revoked only for a contender that needs more: at once if its risk level is lower (a
  high-risk drone never waits while a lower-risk drone holds a grant), after `min_hold_s` if only its
  latency is lower, and after `rotate_after_s` if the two need the same (equals take turns, so no
  drone whose need stays highest waits for ever);
- a drone that no longer wants priority but whose session is in its hold-down keeps its place until
  anyone else needs it;
- when a contender cannot be placed yet, nobody who needs less is granted in its stead (one that would
  not fit even alone blocks nobody): so a drone can wait while a lower risk holds a grant only when a
  drone that needs more than it is waiting too, for room that revoking the lower risk would not make;
- if a holder's offered rate grows past the budget, the lowest need is revoked until it fits again.

Decisions are deterministic for a given sequence of inputs: ties end in the order drones began to wait,
then by id.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass

from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.config import ArbiterConfig

# Risk levels as the arbiter ranks them; 0 is a drone in its hold-down (it wants nothing any more).
RISK_LEVELS = {"HR": 3, "MR": 2, "NA": 2, "LR": 1}
LINGERING = 0
EXCESS_STEP = 0.1  # latency over the threshold, in steps of P_lat


class Action(str, enum.Enum):
    GRANT = "grant"
    DENY = "deny"
    REVOKE = "revoke"
    RELEASE = "release"


@dataclass(frozen=True, slots=True)
class Need:
    """One drone's case for priority, from its latest QosRequest (or its hold-down)."""

    risk: str = "NA"  # the supervisor's risk level: HR, MR, LR or NA
    latency_excess: float = 0.0  # P_lat minus the supervisor's th_lat (> 0: high latency)
    offered_mbps: float = 0.0  # what the drone sends upward now
    lingering: bool = False  # it no longer wants priority; its session is in its hold-down

    @property
    def level(self) -> int:
        return LINGERING if self.lingering else RISK_LEVELS.get(self.risk, RISK_LEVELS["NA"])

    @property
    def rank(self) -> tuple[int, int]:
        if self.lingering:
            return (LINGERING, 0)
        steps = self.latency_excess / EXCESS_STEP if math.isfinite(self.latency_excess) else 0.0
        return (self.level, max(-10, min(10, math.floor(steps))))

    def describe(self) -> str:
        if self.lingering:
            return "in its hold-down"
        return f"{self.risk}, latency {self.latency_excess:+.2f} over threshold"


@dataclass(frozen=True, slots=True)
class Decision:
    uav: str
    action: Action
    reason: str
    need: Need


class Arbiter:
    def __init__(self, config: ArbiterConfig) -> None:
        self.config = config
        self._min_hold_ns = to_ns(config.min_hold_s)
        self._rotate_ns = to_ns(config.rotate_after_s)
        self.holders: dict[str, int] = {}  # uav -> when it was granted
        self.waiting: dict[str, int] = {}  # uav -> when it began to wait
        # Why a waiting drone was last told no, as (kind, holders): a new denial is said (and counted) only
        # when that changes, not each time a holder's latency moves.
        self._told_denied: dict[str, tuple[str, tuple[str, ...]]] = {}
        self.needs: dict[str, Need] = {}
        self.blocked: tuple[int, int] | None = None  # the rank of the neediest drone left waiting last round

    @property
    def budget_mbps(self) -> float:
        """The priority rate the holders may offer together (inf: no rate budget)."""
        if self.config.max_share >= 1.0 or self.config.uplink_mbps <= 0:
            return math.inf
        return self.config.max_share * self.config.uplink_mbps

    def _fits(self, uavs: list[str], needs: Mapping[str, Need]) -> bool:
        if self.config.max_grants >= 0 and len(uavs) > self.config.max_grants:
            return False
        return sum(needs[u].offered_mbps for u in uavs) <= self.budget_mbps + 1e-9

    def decide(self, needs: Mapping[str, Need], now_ns: int) -> list[Decision]:
        """The decisions for the drones' current needs (a drone absent from `needs` wants nothing)."""
        self.needs = dict(needs)
        decisions: list[Decision] = []
        for uav in sorted(self.holders):
            if uav not in needs:
                del self.holders[uav]
                decisions.append(
                    Decision(uav, Action.RELEASE, "no longer wants priority", Need(lingering=True))
                )
        for uav in sorted(self.waiting):
            if uav not in needs or needs[uav].lingering:
                del self.waiting[uav]
                self._told_denied.pop(uav, None)
        decisions += self._shed(needs)
        contenders = [u for u in needs if u not in self.holders and not needs[u].lingering]
        for uav in contenders:
            self.waiting.setdefault(uav, now_ns)
        contenders.sort(key=lambda u: (tuple(-x for x in needs[u].rank), self.waiting[u], u))
        blocked: tuple[int, int] | None = None
        self.blocked = None
        for uav in contenders:
            need = needs[uav]
            if blocked is not None and need.rank < blocked:
                decisions += self._deny(uav, need, "blocked", "a drone that needs it more is waiting")
                continue
            evict = self._make_room(uav, needs, now_ns)
            if evict is None:
                if blocked is None and self._fits([uav], needs):  # one that could never fit blocks nobody
                    blocked = self.blocked = need.rank
                decisions += self._deny(uav, need, "full", self._why_full(uav, needs))
                continue
            for other in evict:
                del self.holders[other]
                reason = f"for {uav} ({need.describe()}); it was {needs[other].describe()}"
                decisions.append(Decision(other, Action.REVOKE, reason, needs[other]))
                if not needs[other].lingering:
                    self.waiting.setdefault(other, now_ns)
            self.holders[uav] = now_ns
            del self.waiting[uav]
            self._told_denied.pop(uav, None)
            decisions.append(Decision(uav, Action.GRANT, need.describe(), need))
        return decisions

    def _shed(self, needs: Mapping[str, Need]) -> list[Decision]:
        """Holders whose rates grew past the budget: the lowest need goes until the rest fit."""
        out: list[Decision] = []
        while self.holders and not self._fits(list(self.holders), needs):
            lowest = min(self.holders, key=lambda u: (needs[u].rank, -self.holders[u], u))
            del self.holders[lowest]
            out.append(Decision(lowest, Action.REVOKE, "the holders' rates exceed the budget", needs[lowest]))
        return out

    def _make_room(self, uav: str, needs: Mapping[str, Need], now_ns: int) -> list[str] | None:
        """The holders to revoke so that `uav` fits ([] if it fits as is), or None if it cannot."""
        if self._fits([*self.holders, uav], needs):
            return []
        if not self._fits([uav], needs):
            return None
        need = needs[uav]
        evictable = [h for h in self.holders if self._yields(h, need, needs[h], now_ns)]
        evictable.sort(key=lambda h: (needs[h].rank, self.holders[h], h))  # least need, longest held first
        out: list[str] = []
        for holder in evictable:
            out.append(holder)
            if self._fits([*(h for h in self.holders if h not in out), uav], needs):
                return out
        return None

    def _yields(self, holder: str, contender: Need, held: Need, now_ns: int) -> bool:
        held_for = now_ns - self.holders[holder]
        if held.level < contender.level:
            return True
        if held.rank < contender.rank:
            return held_for >= self._min_hold_ns
        if held.rank == contender.rank:
            return held_for >= self._rotate_ns
        return False

    def _why_full(self, uav: str, needs: Mapping[str, Need]) -> str:
        if not self._fits([uav], needs):
            return f"it offers {needs[uav].offered_mbps:.1f} Mbit/s, over the whole budget"
        holders = ", ".join(f"{h} ({needs[h].describe()})" for h in sorted(self.holders))
        return f"the budget is held by {holders}"

    def _deny(self, uav: str, need: Need, kind: str, reason: str) -> list[Decision]:
        key = (kind, tuple(sorted(self.holders)))
        if self._told_denied.get(uav) == key:
            return []
        self._told_denied[uav] = key
        return [Decision(uav, Action.DENY, reason, need)]

    def next_change_ns(self, now_ns: int) -> int:
        """When a waiting drone may next be placed without news: a holder's min-hold or turn ends."""
        if not self.waiting:
            return now_ns + NS_PER_S
        ends = [t + d for t in self.holders.values() for d in (self._min_hold_ns, self._rotate_ns)]
        future = [e for e in ends if e > now_ns]
        return min(future) if future else now_ns + NS_PER_S
