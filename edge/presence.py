"""Who is there, from zenoh liveliness tokens: the one place the edge watches them.

Four things are known by tokens: the replicas of a service (MPC, planner: edge/membership.py), the
detectors (`LiveSet`), the QoS agents and the active one (edge/qos/peers.py), and the drones
(`dynqos/<uav>/alive`, edge/feeds.py). Each is a `Presence`: it watches its key expressions, asks the
router for the live set at start (a token declared before the watch would otherwise be missed only by
a slow router), and hands the changes to its one consumer in batches. zenoh reports on its own
threads; a change waits, bounded, in a map (the newest word per token wins) until the consumer's
thread takes it, and `wake` (when given) tells the consumer there is something to take. A flood beyond
the bound, a name that breaks its rule, or a name beyond the cap is refused, counted and logged at
the first and every thousandth (common/floods.py).

Names may also be left to the pure part they feed (`Assignment`, `Leadership` validate and cap
themselves, and are tested for it): then `valid` and `cap` are left out here.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from dynqos.common.bus import Bus
from dynqos.common.floods import worth_logging
from dynqos.common.queues import PendingChanges

log = logging.getLogger(__name__)

QUERY_TIMEOUT_S = 2.0  # the live set asked for at start


@dataclass(frozen=True, slots=True)
class Watch:
    """One kind of token: where it lives and how a key names its holder."""

    kind: str  # "member", "active", "drone": what the consumer calls it
    key_expr: str
    name_of: Callable[[str], str]


@dataclass(frozen=True, slots=True)
class Seen:
    """One holder came or went."""

    kind: str
    name: str
    alive: bool


class Presence:
    def __init__(
        self,
        bus: Bus,
        owner: str,
        watches: Sequence[Watch],
        *,
        pending_limit: int,
        valid: Callable[[str], bool] | None = None,
        cap: int | None = None,
        me: str | None = None,
        wake: Callable[[], None] | None = None,
    ) -> None:
        """`owner` names the consumer in the log; `me` is our own name (never a change); `valid` and
        `cap` bound each kind's set (None: the consumer does)."""
        self.owner = owner
        self.watches = tuple(watches)
        self.valid = valid
        self.cap = cap
        self.me = me
        self.present: dict[str, set[str]] = {w.kind: set() for w in self.watches}
        self._refused_names = 0
        self._wake = wake
        self._bus = bus
        self._pending: PendingChanges[tuple[str, str]] = PendingChanges(pending_limit)
        for watch in self.watches:
            bus.watch_tokens(watch.key_expr, functools.partial(self._on_token, watch))

    def query(self, timeout_s: float = QUERY_TIMEOUT_S) -> None:
        """The live set as the router knows it now (blocking: off any event loop)."""
        for watch in self.watches:
            for key in self._bus.alive_tokens(watch.key_expr, timeout_s=timeout_s):
                self._on_token(watch, key, True)

    def _on_token(self, watch: Watch, key: str, alive: bool) -> None:
        """zenoh's thread: note the change; the consumer takes it."""
        if self._pending.offer((watch.kind, watch.name_of(key)), alive) and self._wake is not None:
            self._wake()

    @property
    def refused(self) -> int:
        """Tokens refused here: beyond the pending bound, an invalid name, beyond the cap."""
        return self._pending.refused + self._refused_names

    def take(self) -> list[Seen]:
        """The consumer's thread: what changed since the last call, in the order zenoh said it."""
        seen = []
        for (kind, name), alive in self._pending.take().items():
            group = self.present[kind]
            if name == self.me or alive == (name in group):
                continue
            if alive and not self._admit(kind, name, group):
                continue
            if alive:
                group.add(name)
            else:
                group.discard(name)
            seen.append(Seen(kind, name, alive))
        return seen

    def _admit(self, kind: str, name: str, group: set[str]) -> bool:
        if (self.valid is None or self.valid(name)) and (self.cap is None or len(group) < self.cap):
            return True
        self._refused_names += 1
        if worth_logging(self._refused_names):
            log.warning(
                "%s: %s token %r refused (invalid name or more than %s; %d so far)",
                self.owner,
                kind,
                name[:120],
                self.cap,
                self._refused_names,
            )
        return False
