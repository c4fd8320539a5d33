"""The I/O shell of edge/replicas.py: one replica's liveliness token, and the live set as zenoh reports
it, handed to the pure Assignment on the service's own worker thread; and `LiveSet`, the same tokens
for a best-effort service that needs no standby.

The token is declared, the live set queried (so that a replica does not serve before it knows its
peers) and then watched. Changes arrive on zenoh's thread and wait, bounded, in a map the worker
drains; a flood beyond the bound is refused and counted.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import threading
from collections.abc import Collection

from dynqos.common import keys
from dynqos.common.bus import Bus
from dynqos.common.queues import PendingChanges
from dynqos.edge.replicas import MAX_REPLICAS, Assignment, Change, Role, ranked, valid_replica_id

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
        self._pending: PendingChanges[str] = PendingChanges(MAX_PENDING_CHANGES)
        bus.watch_tokens(keys.replicas_of(service, group), self._on_token)
        self.token = bus.declare_token(keys.replica_token(service, group, self.replica))
        for key in bus.alive_tokens(keys.replicas_of(service, group), timeout_s=2.0):  # the live set first
            self._on_token(key, True)

    def _on_token(self, key: str, alive: bool) -> None:
        """zenoh's thread: note the change; the worker applies it (the assignment is not shared)."""
        self._pending.offer(key, alive)

    @property
    def refused(self) -> int:
        """Changes beyond MAX_PENDING_CHANGES."""
        return self._pending.refused

    def apply(self) -> None:
        """The worker: the changes since the last call, into the assignment, each logged."""
        changes = self._pending.take()
        a = self.assignment
        for key, alive in changes.items():
            replica = keys.replica_of_token(key)
            live = len(a.members)
            if alive and a.join(replica):
                log.info("%s %s: replica %s joined (%d live)", self.service, self.replica, replica, live + 1)
                self._changed = True
            elif not alive and a.leave(replica):
                log.info("%s %s: replica %s left (%d live)", self.service, self.replica, replica, live - 1)
                self._changed = True
            elif alive and replica not in a.members and replica != self.replica:
                refused = a.counters.members_refused
                if refused == 1 or refused % 1000 == 0:  # a flood is logged once, and counted
                    log.warning("%s %s: replica token %r refused (invalid or too many; %d so far)",
                                self.service, self.replica, key[:120], refused)  # fmt: skip

    def log_change(self, change: Change | None) -> None:
        if change is not None:
            self._changed = True
            log.info("%s %s: drone %s: %s (term %d, now %s)", self.service, self.replica, change.uav,
                     change.reason, change.term, change.role.value)  # fmt: skip

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
    token goes. zenoh's thread replaces the set whole; readers take it without a lock."""

    def __init__(self, service: str, replica: str, bus: Bus) -> None:
        if not valid_replica_id(replica):
            raise ValueError(f"replica id {replica[:80]!r} is invalid: use 1 to 64 of A-Z a-z 0-9 _ -")
        self.service = service
        self.me = replica
        self.refused = 0  # tokens with an invalid name or beyond MAX_REPLICAS
        self._lock = threading.Lock()
        # the live set, and per drone whether this replica serves it for that set: replaced together
        self._state: tuple[frozenset[str], dict[str, bool]] = (frozenset({replica}), {})
        bus.watch_tokens(keys.replicas_of(service), self._on_token)
        self.token = bus.declare_token(keys.replica_token(service, "all", replica))
        for key in bus.alive_tokens(keys.replicas_of(service), timeout_s=2.0):
            self._on_token(key, True)

    def _on_token(self, key: str, alive: bool) -> None:
        replica = keys.replica_of_token(key)
        with self._lock:
            members = set(self._state[0])
            if alive and replica not in members:
                if not valid_replica_id(replica) or len(members) >= MAX_REPLICAS:
                    self.refused += 1
                    return
                members.add(replica)
            elif not alive and replica in members and replica != self.me:
                members.discard(replica)
            else:
                return
            self._state = (frozenset(members), {})
        log.info("%s %s: replica %s %s (%d live)", self.service, self.me, replica,
                 "joined" if alive else "left", len(members))  # fmt: skip

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
