"""Load for the cell benchmarks and tests: a paced TCP sender and a counting sink, on 127.0.0.1.

Every loop is bounded in time; the sink's threads stop on close().
"""

from __future__ import annotations

import socket
import threading
import time


class Sink:
    """A TCP server that reads everything and records (time, cumulative bytes)."""

    def __init__(self) -> None:
        self.total = 0
        self.samples: list[tuple[float, int]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._server = socket.socket()
        self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._server.bind(("127.0.0.1", 0))
        self._server.listen(8)
        self._server.settimeout(0.2)
        self.port: int = self._server.getsockname()[1]
        self._threads = [threading.Thread(target=self._accept, daemon=True)]
        self._threads[0].start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            thread = threading.Thread(target=self._read, args=(conn,), daemon=True)
            thread.start()
            self._threads.append(thread)

    def _read(self, conn: socket.socket) -> None:
        conn.settimeout(0.2)
        with conn:
            while not self._stop.is_set():
                try:
                    data = conn.recv(65536)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not data:
                    return
                with self._lock:
                    self.total += len(data)
                    self.samples.append((time.monotonic(), self.total))

    def rate_mbps(self, t0: float, t1: float) -> float:
        with self._lock:
            before = [b for t, b in self.samples if t <= t0]
            upto = [b for t, b in self.samples if t <= t1]
        start = before[-1] if before else 0
        end = upto[-1] if upto else 0
        return (end - start) * 8 / (t1 - t0) / 1e6

    def close(self) -> None:
        self._stop.set()
        self._server.close()
        for thread in self._threads:
            thread.join(timeout=5)


def send_paced(port: int, rate_bps: float, duration_s: float, chunk: int = 16 * 1024) -> int:
    """Offer rate_bps to 127.0.0.1:port for duration_s (back-pressure may slow it); returns bytes sent."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 64 * 1024)
    payload = bytes(chunk)
    sent = 0
    start = time.monotonic()
    try:
        while (now := time.monotonic()) - start < duration_s:
            due = start + sent * 8 / rate_bps
            if due > now:
                time.sleep(min(due - now, 0.01))  # pacing the offered load, not synchronisation
                continue
            sock.sendall(payload)
            sent += chunk
    finally:
        sock.close()
    return sent
