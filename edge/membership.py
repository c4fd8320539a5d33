"""The I/O shell of edge/replicas.py: one replica's liveliness token, and the live set as zenoh reports
it, handed to the pure Assignment on the service's own worker thread.

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
from dynqos.edge.replicas import Assignment, Change, Role

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
        self.refused = 0  # changes beyond MAX_PENDING_CHANGES
        self._pending: dict[str, bool] = {}
        self._lock = threading.Lock()
        bus.watch_tokens(keys.replicas_of(service, group), self._on_token)
        self.token = bus.declare_token(keys.replica_token(service, group, self.replica))
        for key in bus.alive_tokens(keys.replicas_of(service, group), timeout_s=2.0):  # the live set first
            self._on_token(key, True)

    def _on_token(self, key: str, alive: bool) -> None:
        """zenoh's thread: note the change; the worker applies it (the assignment is not shared)."""
        with self._lock:
            if key not in self._pending and len(self._pending) >= MAX_PENDING_CHANGES:
                self.refused += 1
                return
            self._pending[key] = alive

    def apply(self) -> None:
        """The worker: the changes since the last call, into the assignment, each logged."""
        with self._lock:
            changes, self._pending = self._pending, {}
        a = self.assignment
        for key, alive in changes.items():
            replica = keys.replica_of_token(key)
            live = len(a.members)
            if alive and a.join(replica):
                log.info("%s %s: replica %s joined (%d live)", self.service, self.replica, replica, live + 1)
            elif not alive and a.leave(replica):
                log.info("%s %s: replica %s left (%d live)", self.service, self.replica, replica, live - 1)
            elif alive and replica not in a.members and replica != self.replica:
                refused = a.counters.members_refused
                if refused == 1 or refused % 1000 == 0:  # a flood is logged once, and counted
                    log.warning("%s %s: replica token %r refused (invalid or too many; %d so far)",
                                self.service, self.replica, key[:120], refused)  # fmt: skip

    def log_change(self, change: Change | None) -> None:
        if change is not None:
            log.info("%s %s: drone %s: %s (term %d, now %s)", self.service, self.replica, change.uav,
                     change.reason, change.term, change.role.value)  # fmt: skip

    def health(self, drones: Collection[str], serving_word: str) -> str:
        """The replica part of a health line: who this is, how many peers, and its drones by role."""
        a = self.assignment
        serving = sum(1 for uav in drones if a.role(uav) is Role.SERVE)
        return (
            f"replica={self.replica} replicas={len(a.members)} {serving_word}={serving} "
            f"standby={len(drones) - serving} takeovers={a.counters.takeovers}"
        )
