"""systemd's notify protocol for the onboard daemon: READY, STATUS, WATCHDOG, STOPPING."""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)


class SystemdNotifier:
    """sd_notify over $NOTIFY_SOCKET when systemd started us (Type=notify, WatchdogSec).

    Fifteen lines of protocol rather than a dependency: the `sdnotify` package is unmaintained and
    systemd-python needs libsystemd headers on the companion computer. The watchdog is fed from the
    50 Hz control loop at half of $WATCHDOG_USEC, so a stalled loop (not just a dead process) restarts.
    """

    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) if self.address else None
        usec = os.environ.get("WATCHDOG_USEC", "")
        self.watchdog_interval_ns = int(usec) * 1000 // 2 if usec.isdigit() and int(usec) > 0 else None
        self._next_watchdog_ns = 0

    def feed_watchdog(self, now_ns: int) -> None:
        if self.watchdog_interval_ns is not None and now_ns >= self._next_watchdog_ns:
            self._next_watchdog_ns = now_ns + self.watchdog_interval_ns
            self.notify("WATCHDOG=1")

    def notify(self, text: str) -> None:
        if self.sock is not None:
            try:
                self.sock.sendto(text.encode(), self.address)
            except OSError as exc:
                log.debug("sd_notify failed: %s", exc)
