"""The UDP ports a flight's vehicles and daemons meet on (dynqos/experiment/processes.py): chosen outside
the kernel's ephemeral range, so that no socket bound to port 0 (a vehicle's own end, chosen when it
starts and before the daemon it talks to has bound its port) can be handed one of them."""

from __future__ import annotations

import random
import socket
from pathlib import Path

from dynqos.experiment.processes import EPHEMERAL_FALLBACK, ephemeral_ports, free_udp_block


def test_a_block_lies_outside_the_ephemeral_range_and_every_port_of_it_binds() -> None:
    low, high = ephemeral_ports()
    for _ in range(20):
        base = free_udp_block(5)
        assert base + 4 < low or base > high, (base, low, high)
        socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(5)]
        try:
            for port, sock in enumerate(socks, start=base):
                sock.bind(("127.0.0.1", port))
        finally:
            for sock in socks:
                sock.close()


def test_a_port_bound_to_zero_is_never_one_of_the_block() -> None:
    """What went wrong: a vehicle's bind to port 0 landed on the port chosen for its daemon."""
    base = free_udp_block(4)
    taken = []
    try:
        for _ in range(300):  # the kernel's picks while the block is unbound, as a starting fleet's are
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
            taken.append(sock)
        assert not {s.getsockname()[1] for s in taken} & set(range(base, base + 4))
    finally:
        for sock in taken:
            sock.close()


def test_a_block_already_taken_is_passed_over() -> None:
    low, high = ephemeral_ports()
    first = free_udp_block(3, rng=random.Random(7))
    held = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    try:
        for port, sock in enumerate(held, start=first):
            sock.bind(("127.0.0.1", port))
        again = free_udp_block(3, rng=random.Random(7))  # the same first draw: taken, so the next
        assert again != first
        assert again + 2 < low or again > high
    finally:
        for sock in held:
            sock.close()


def test_the_range_is_read_from_the_kernel_or_linuxs_default(tmp_path: Path) -> None:
    ranges = tmp_path / "ip_local_port_range"
    ranges.write_text("20000\t40000\n")
    assert ephemeral_ports(ranges) == (20000, 40000)
    ranges.write_text("garbage\n")
    assert ephemeral_ports(ranges) == EPHEMERAL_FALLBACK
    assert ephemeral_ports(tmp_path / "absent") == EPHEMERAL_FALLBACK


def test_a_range_that_leaves_no_room_falls_back_to_any_free_block() -> None:
    base = free_udp_block(2, ephemeral=(1024, 65535))
    assert 0 < base < 65535
