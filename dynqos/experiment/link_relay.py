"""The link between two edge sites' routers, relayed by the runner so that a fault can cut it.

Site B's router links to site A's (`[zenoh] router_links`) through this relay when a scenario has a
`path_partition` fault: one TCP relay on 127.0.0.1, forwarding each connection to router A's port.
`cut` closes every relayed connection at once and refuses new ones until `mend`: the routers see their
link drop (as a partition between two sites' networks shows it) and router B's zenoh retries its link,
which succeeds once the relay is mended. Bounded: at most MAX_CONNECTIONS at once (zenoh opens one per
link), each pumped by two daemon threads, all closed by `close`.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading

log = logging.getLogger(__name__)

MAX_CONNECTIONS = 8
CHUNK = 65536
CONNECT_TIMEOUT_S = 2.0


class LinkRelay:
    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._open: list[socket.socket] = []  # both ends of every relayed connection
        self._cut = False
        self._closed = False
        self.relayed = 0  # connections relayed so far
        self.refused = 0  # connections closed at once: while cut, or beyond MAX_CONNECTIONS
        threading.Thread(target=self._accept, name="link-relay", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:
                return  # closed
            with self._lock:
                refuse = self._cut or self._closed or len(self._open) >= 2 * MAX_CONNECTIONS
            if refuse:
                self.refused += 1
                conn.close()
                continue
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target_port), CONNECT_TIMEOUT_S)
            except OSError:
                conn.close()  # router A is down (a site kill): the linking router retries
                continue
            upstream.settimeout(None)
            with self._lock:
                self._open += [conn, upstream]
                self.relayed += 1
            for src, dst in ((conn, upstream), (upstream, conn)):
                threading.Thread(
                    target=self._pump, args=(src, dst), name="link-relay-pump", daemon=True
                ).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(CHUNK):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            self._drop(src, dst)

    def _drop(self, *socks: socket.socket) -> None:
        with self._lock:
            self._open = [s for s in self._open if s not in socks]
        for s in socks:
            with contextlib.suppress(OSError):
                s.shutdown(socket.SHUT_RDWR)
            s.close()

    def cut(self) -> int:
        """Close every relayed connection and refuse new ones; how many connections were cut."""
        with self._lock:
            self._cut = True
            cut, self._open = list(self._open), []
        self._drop(*cut)
        log.info("link relay: the link between the sites cut (%d connection(s))", len(cut) // 2)
        return len(cut) // 2

    def mend(self) -> None:
        with self._lock:
            self._cut = False
        log.info("link relay: the link between the sites mended")

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self.cut()
        with contextlib.suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)  # wakes the accepting thread (close alone does not)
        self._listener.close()
