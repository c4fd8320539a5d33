"""The I/O shell of edge/replicas.py: one replica's liveliness token, and the live set as zenoh reports
it, handed to the pure Assignment on the service's own worker thread; and `LiveSet`, the same tokens
for a best-effort service that needs no standby.

The token is declared, the live set queried (so that a replica does not serve before it knows its
peers) and then watched, by edge/presence.py; the worker applies the changes.
"""

from __future__ import annotations

import logging
import os
import re
import socket
from collections.abc import Collection

from dynqos.common import keys
from dynqos.common.bus import Bus
from dynqos.common.floods import worth_logging
from dynqos.common.keys import check_replica_id, valid_replica_id
from dynqos.edge.presence import Presence, Watch
from dynqos.edge.replicas import MAX_REPLICAS, Assignment, Change, Role, ranked

log = logging.getLogger(__name__)

MAX_PENDING_CHANGES = 1024  # token changes waiting for the worker; a flood beyond is refused


def default_replica_id() -> str:
    """`<host>-<pid>`: unique on a machine and, under Kubernetes, across pods (the host is the pod)."""
    host = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname())[:40] or "host"
    return f"{host}-{os.getpid()}"


class Membership:
    def __init__(self, service: str, group: str, assignment: Assignment, bus: Bus) -> None:
        self.service = service
        self.assignment = assignment
        self.replica = assignment.me
        self._changed = False  # a replica joined or left, or this replica's role for a drone changed
        # names are the Assignment's to validate and cap (its members_refused)
        self.presence = Presence(
            bus,
            f"{service} {self.replica}",
            [Watch("member", keys.replicas_of(service, group), keys.replica_of_token)],
            pending_limit=MAX_PENDING_CHANGES,
            me=self.replica,
        )
        self.token = bus.declare_token(keys.replica_token(service, group, self.replica))
        self.presence.query()  # the live set first: a replica does not serve before it knows its peers

    @property
    def refused(self) -> int:
        """Changes beyond MAX_PENDING_CHANGES."""
        return self.presence.refused

    def apply(self) -> None:
        """The worker: the changes since the last call, into the assignment, each logged."""
        a = self.assignment
        for seen in self.presence.take():
            me, peer, live = self.replica, seen.name, len(a.members)
            if seen.alive and a.join(peer):
                log.info("%s %s: replica %s joined (%d live)", self.service, me, peer, live + 1)
                self._changed = True
            elif not seen.alive and a.leave(peer):
                log.info("%s %s: replica %s left (%d live)", self.service, me, peer, live - 1)
                self._changed = True
            elif seen.alive and worth_logging(refused := a.counters.members_refused):
                log.warning(
                    "%s %s: replica %r refused (invalid or too many; %d so far)",
                    self.service,
                    self.replica,
                    seen.name[:120],
                    refused,
                )

    def log_change(self, change: Change | None) -> None:
        if change is not None:
            self._changed = True
            log.info(
                "%s %s: drone %s: %s (term %d, now %s)",
                self.service,
                self.replica,
                change.uav,
                change.reason,
                change.term,
                change.role.value,
            )

    @property
    def changed(self) -> bool:
        """Whether the live set or a role changed since the last `take_changed` (without taking it)."""
        return self._changed

    def take_changed(self) -> bool:
        """Whether the live set or a role changed since the last call (which drones to follow)."""
        changed, self._changed = self._changed, False
        return changed

    def health(self, drones: Collection[str], serving_word: str) -> str:
        """The replica part of a health line: who this is, how many peers, and its drones by role."""
        a = self.assignment
        serving = sum(1 for uav in drones if a.role(uav) is Role.SERVE)
        return (
            f"replica={self.replica} replicas={len(a.members)} {serving_word}={serving} "
            f"standby={len(drones) - serving} takeovers={a.counters.takeovers}"
        )


class LiveSet:
    """The live replicas of a best-effort service (the detector): no standby, no terms; each drone is
    served by the first-ranked live replica (rendezvous order), and by another as soon as that one's
    token goes. The service's thread applies the changes (`apply`) before it asks who serves."""

    def __init__(self, service: str, replica: str, bus: Bus) -> None:
        check_replica_id(replica)
        self.service = service
        self.me = replica
        self.presence = Presence(
            bus,
            f"{service} {replica}",
            [Watch("member", keys.replicas_of(service), keys.replica_of_token)],
            pending_limit=MAX_PENDING_CHANGES,
            valid=valid_replica_id,
            cap=MAX_REPLICAS - 1,
            me=replica,
        )
        # the live set, and per drone whether this replica serves it for that set: replaced together
        self._state: tuple[frozenset[str], dict[str, bool]] = (frozenset({replica}), {})
        self.token = bus.declare_token(keys.replica_token(service, "all", replica))
        self.presence.query()
        self.apply()

    @property
    def refused(self) -> int:
        """Tokens with an invalid name, beyond MAX_REPLICAS, or beyond the pending bound."""
        return self.presence.refused

    def apply(self) -> None:
        """The service's thread: the changes since the last call, each logged."""
        changes = self.presence.take()
        if not changes:
            return
        members = frozenset(self.presence.present["member"] | {self.me})
        self._state = (members, {})
        for seen in changes:
            log.info(
                "%s %s: replica %s %s (%d live)",
                self.service,
                self.me,
                seen.name,
                "joined" if seen.alive else "left",
                len(members),
            )

    def serves(self, uav: str) -> bool:
        """Whether this replica serves `uav` now (cached per drone until the set changes)."""
        members, cache = self._state
        first = cache.get(uav)
        if first is None:
            if len(cache) >= 4096:  # drone ids from the wire: bounded
                cache.clear()
            first = cache[uav] = ranked(uav, members)[0] == self.me
        return first

    @property
    def members(self) -> frozenset[str]:
        return self._state[0]

    def close(self) -> None:
        self.token.close()
