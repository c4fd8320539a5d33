"""The relay the runner puts between two sites' routers (dynqos/experiment/link_relay.py): it relays
bytes both ways; `cut` ends every relayed connection and refuses new ones; `mend` lets them through
again. Over loopback, against a plain echo server standing in for router A's port."""

from __future__ import annotations

import contextlib
import socket
import threading
from collections.abc import Iterator

import pytest

from dynqos.experiment.link_relay import LinkRelay

pytestmark = pytest.mark.timeout(30)


@contextlib.contextmanager
def echo_server() -> Iterator[int]:
    server = socket.create_server(("127.0.0.1", 0))
    done = threading.Event()

    def serve() -> None:
        while not done.is_set():
            try:
                conn, _ = server.accept()
            except OSError:
                return
            threading.Thread(target=echo, args=(conn,), daemon=True).start()

    def echo(conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            while data := conn.recv(4096):
                conn.sendall(data)

    threading.Thread(target=serve, daemon=True).start()
    try:
        yield server.getsockname()[1]
    finally:
        done.set()
        with contextlib.suppress(OSError):
            server.shutdown(socket.SHUT_RDWR)
        server.close()


def through(port: int, payload: bytes) -> bytes:
    """`payload` sent through a new connection to `port`, and what came back before it closed or
    answered ("" when the relay closed it at once)."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as conn:
        try:
            conn.sendall(payload)
            return conn.recv(4096)
        except (ConnectionResetError, BrokenPipeError):
            return b""


def test_the_relay_carries_both_ways_cut_ends_every_link_and_mend_lets_them_through() -> None:
    with echo_server() as port:
        relay = LinkRelay(port)
        try:
            link = socket.create_connection(("127.0.0.1", relay.port), timeout=5)
            link.sendall(b"hello")
            assert link.recv(4096) == b"hello"
            assert relay.cut() == 1
            assert link.recv(4096) == b""  # the live link ended: the routers see it drop
            link.close()
            assert through(relay.port, b"again") == b""  # refused while cut
            assert relay.refused == 1
            relay.mend()
            assert through(relay.port, b"back") == b"back"
            assert relay.relayed == 2
        finally:
            relay.close()
