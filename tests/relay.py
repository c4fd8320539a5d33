"""A TCP relay for tests: counts the bytes of each direction and can pace the upstream direction.

It stands between a zenoh session and a router port, so a test can see which link carried which
traffic, and can make one link slow (like a loaded bearer) to check that priority traffic on the
other link is not held up. The real cell emulator lives in `sim/`; this is a measuring tap.
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time

CHUNK = 16 * 1024
SMALL_BUFFER = 32 * 1024


class Relay:
    def __init__(self, target_port: int, *, up_rate_bps: float | None = None) -> None:
        self.target = ("127.0.0.1", target_port)
        self.up_rate_bps = up_rate_bps
        self.up_bytes = 0
        self.down_bytes = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SMALL_BUFFER)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(8)
        self._listener.settimeout(0.2)
        self.port: int = self._listener.getsockname()[1]
        self._spawn(self._accept_loop)

    def _spawn(self, target: object, *args: object) -> None:
        thread = threading.Thread(target=target, args=args, daemon=True)  # type: ignore[arg-type]
        thread.start()
        self._threads.append(thread)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            try:
                client, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            upstream = socket.create_connection(self.target, timeout=5)
            for sock in (client, upstream):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SMALL_BUFFER)
                sock.settimeout(0.2)
            with self._lock:
                self._sockets += [client, upstream]
            self._spawn(self._pump, client, upstream, True)
            self._spawn(self._pump, upstream, client, False)

    def _pump(self, src: socket.socket, dst: socket.socket, upward: bool) -> None:
        next_free = time.monotonic()
        while not self._stop.is_set():
            try:
                data = src.recv(CHUNK)
            except TimeoutError:
                continue
            except OSError:
                break
            if not data:
                break
            with self._lock:  # counted before it is passed on: a reader that has the bytes sees them counted
                if upward:
                    self.up_bytes += len(data)
                else:
                    self.down_bytes += len(data)
            try:
                dst.sendall(data)
            except OSError:
                break
            if upward and self.up_rate_bps:
                # Pace the reads: this is the emulated link rate, not synchronisation.
                # A token bucket with 10 ms of burst: an idle link saves up no more credit than that.
                now = time.monotonic()
                next_free = max(next_free, now - 0.01) + len(data) * 8 / self.up_rate_bps
                if next_free > now:
                    self._stop.wait(next_free - now)
        for sock in (src, dst):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    def counters(self) -> tuple[int, int]:
        with self._lock:
            return self.up_bytes, self.down_bytes

    def close(self) -> None:
        self._stop.set()
        self._listener.close()
        with self._lock:
            sockets = list(self._sockets)
        for sock in sockets:
            sock.close()
        for thread in self._threads:
            thread.join(timeout=5)

    def __enter__(self) -> Relay:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
