"""Test rig for the cell emulator: the emulator as a real process, a paced sender and a counting sink.

Everything listens on 127.0.0.1; every loop is bounded in time; the emulator is stopped by its pid.
"""

from __future__ import annotations

import json
import socket
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

from tests.procs import DynqosProcess


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


class CellProcess(DynqosProcess):
    """`dynqos sim cell` in its own process, started from a TOML text, stopped by its pid."""

    def __init__(self, tmp_path: Path, toml: str, duration_s: float = 60.0, out: Path | None = None) -> None:
        config = tmp_path / "cell.toml"
        config.write_text(toml)
        args = ["sim", "cell", "--duration", str(duration_s)]
        if out is not None:
            args += ["--out", str(out)]
        super().__init__(args, config)

    def port(self, bearer: str) -> int:
        port: int = self.info["bearers"][bearer]["port"]
        return port

    def counters(self) -> dict[str, Any]:
        url = f"http://127.0.0.1:{self.info['control_port']}/counters"
        with urllib.request.urlopen(url, timeout=5) as response:
            data: dict[str, Any] = json.loads(response.read())
            return data

    def post_event(self, event: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        request = urllib.request.Request(
            f"http://127.0.0.1:{self.info['control_port']}/events",
            data=json.dumps(event).encode(),
            method="POST",
            headers={"Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as response:
                return response.status, json.loads(response.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def __enter__(self) -> CellProcess:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()
