"""Real zenoh sessions on 127.0.0.1: a router with the two flow ports and a drone peer session.

Relays in front of the router ports count which link carried which bytes (docs/architecture.md).
"""

from __future__ import annotations

import json
import statistics
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from dynqos.common import keys
from dynqos.common.clock import MonotonicClock
from dynqos.common.config import ZenohConfig
from dynqos.common.errors import TransportError
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import CameraFrame, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import (
    Bus,
    Priority,
    Received,
    Role,
    close_session,
    default_flow_endpoint,
    open_bus,
    priority_flow_endpoint,
    session_config,
)
from tests.conftest import flow_ports
from tests.relay import Relay

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

UAV = "uav1"
CHUNK = 100_000


@dataclass
class Net:
    cfg: ZenohConfig
    router: Bus
    edge: Bus
    drone: Bus
    default_relay: Relay
    priority_relay: Relay


def _open(up_rate_bps: float | None = None) -> Iterator[Net]:
    cfg = ZenohConfig(**flow_ports())
    router = open_bus(cfg, Role.ROUTER)
    default_relay = Relay(cfg.default_port, up_rate_bps=up_rate_bps)
    priority_relay = Relay(cfg.priority_port)
    edge = drone = None
    try:
        edge = open_bus(cfg, Role.EDGE)
        drone = open_bus(
            cfg,
            Role.DRONE,
            connect=[
                default_flow_endpoint(cfg, port=default_relay.port),
                priority_flow_endpoint(cfg, port=priority_relay.port),
            ],
        )
        yield Net(cfg, router, edge, drone, default_relay, priority_relay)
    finally:
        for bus in (drone, edge):
            if bus is not None:
                bus.close()
        default_relay.close()
        priority_relay.close()
        router.close()


@pytest.fixture
def net() -> Iterator[Net]:
    yield from _open()


@pytest.fixture
def slow_default_net() -> Iterator[Net]:
    yield from _open(up_rate_bps=10e6)


def test_drone_session_has_exactly_two_links_with_their_priority_ranges(net: Net) -> None:
    links = net.drone.links()
    assert len(links) == 2, links
    by_port = {int(link.dst.split("?")[0].rsplit(":", 1)[1]): link for link in links}
    assert by_port[net.default_relay.port].priorities == (4, 7)
    assert by_port[net.priority_relay.port].priorities == (1, 3)
    router_ranges = sorted(link.priorities or (0, 0) for link in net.router.links())
    assert (1, 3) in router_ranges
    assert (4, 7) in router_ranges


def _frame(seq: int, payload: bytes) -> CameraFrame:
    return CameraFrame(
        uav=UAV, seq=seq, stamp_ns=time.monotonic_ns(), kind="rgb", encoding="jpeg",
        width=640, height=480, intrinsics=(518.0, 519.0, 325.5, 253.5), payload=payload,
    )  # fmt: skip


def _send_and_count(net: Net, flow: Flow, priority: Priority, count: int) -> tuple[int, int]:
    queue: BoundedQueue[Received] = BoundedQueue(count + 10)
    done = threading.Event()
    received: list[int] = []

    stats = net.edge.subscribe(keys.uplink_any_flow(UAV, Stream.CAMERA_RGB), queue)
    publisher = net.drone.publisher(keys.uplink(UAV, flow, Stream.CAMERA_RGB), priority)
    assert publisher.wait_matched(10), "the edge subscriber never matched"
    # Matching says a route exists at our end, yet the first put right after it is now and then lost
    # (seen once in ~20 runs); a delivered warm-up message says the route exists end to end.
    warm = None
    for _ in range(20):
        publisher.put(_frame(10**6, b"warm-up"))
        warm = queue.get(timeout_s=0.5)
        if warm is not None:
            break
    assert warm is not None, "no warm-up message arrived in 10 s"
    queue.drain()
    before_default = net.default_relay.counters()[0]
    before_priority = net.priority_relay.counters()[0]

    def consume() -> None:
        while len(received) < count:
            item = queue.get(timeout_s=20)
            if item is None:
                return
            received.append(item.message.seq)
        done.set()

    consumer = threading.Thread(target=consume)
    consumer.start()
    payload = bytes(CHUNK)
    for seq in range(count):
        publisher.put(_frame(seq, payload))
    assert done.wait(30), f"received {len(received)} of {count}"
    consumer.join(timeout=5)
    publisher.close()
    assert received == list(range(count))
    assert stats.rejected == 0
    return (
        net.default_relay.counters()[0] - before_default,
        net.priority_relay.counters()[0] - before_priority,
    )


def test_wait_matched_says_no_until_a_subscriber_is_there(net: Net) -> None:
    """zenoh's matching status is an object (always truthy): the answer is its `matching` field."""
    publisher = net.drone.publisher(keys.uplink(UAV, Flow.DEFAULT, Stream.STATUS), Priority.DATA)
    assert publisher.wait_matched(0.3) is False  # nobody subscribes to it
    queue: BoundedQueue[Received] = BoundedQueue(4)
    net.edge.subscribe(keys.uplink_any_flow(UAV, Stream.STATUS), queue)
    assert publisher.wait_matched(10) is True


def test_priority_flow_traffic_moves_only_on_the_priority_link(net: Net) -> None:
    on_default, on_priority = _send_and_count(net, Flow.PRIORITY, Priority.INTERACTIVE_LOW, 50)
    assert on_priority >= 50 * CHUNK
    assert on_default < 100_000, "priority-flow bytes leaked onto the default link"


def test_default_flow_traffic_moves_only_on_the_default_link(net: Net) -> None:
    on_default, on_priority = _send_and_count(net, Flow.DEFAULT, Priority.DATA, 50)
    assert on_default >= 50 * CHUNK
    assert on_priority < 100_000, "default-flow bytes leaked onto the priority link"


def test_real_time_state_arrives_promptly_while_bulk_congests_the_default_link(slow_default_net: Net) -> None:
    net = slow_default_net
    clock = MonotonicClock()
    state_queue: BoundedQueue[Received] = BoundedQueue(100)
    bulk_queue: BoundedQueue[Received] = BoundedQueue(1000)
    net.edge.subscribe(keys.uplink_any_flow(UAV, Stream.STATE), state_queue)
    net.edge.subscribe(keys.uplink_any_flow(UAV, Stream.CAMERA_RGB), bulk_queue)
    state_pub = net.drone.publisher(
        keys.uplink(UAV, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME, express=True
    )
    bulk_pub = net.drone.publisher(keys.uplink(UAV, Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA_LOW)
    assert state_pub.wait_matched(10)
    assert bulk_pub.wait_matched(10)

    stop = threading.Event()
    bulk_sent = threading.Event()

    def bulk() -> None:  # bounded: at most 60 x 100 kB (6 MB, ~5 s at 10 Mbit/s)
        payload = bytes(CHUNK)
        for seq in range(60):
            if stop.is_set():
                return
            bulk_pub.put(_frame(seq, payload))
            if seq == 10:
                bulk_sent.set()

    sender = threading.Thread(target=bulk)
    sender.start()
    try:
        assert bulk_sent.wait(20), "bulk stream did not start"
        state_latencies_ms = []
        for seq in range(20):
            sent_ns = clock.now_ns()
            state_pub.put(State(uav=UAV, seq=seq, stamp_ns=sent_ns, pos_m=(0, 0, -1), vel_mps=(0, 0, 0),
                                quat=(1, 0, 0, 0)))  # fmt: skip
            item = state_queue.get(timeout_s=5)
            assert item is not None, f"state {seq} never arrived"
            state_latencies_ms.append((item.arrival_ns - sent_ns) / 1e6)
    finally:
        sender.join(timeout=30)
        stop.set()
    assert not sender.is_alive()
    bulk_latencies_ms = []
    while len(bulk_latencies_ms) < 60:
        item = bulk_queue.get(timeout_s=20)
        assert item is not None, f"bulk message {len(bulk_latencies_ms)} never arrived"
        bulk_latencies_ms.append((item.arrival_ns - item.message.stamp_ns) / 1e6)  # type: ignore[attr-defined]
    state_p50 = statistics.median(state_latencies_ms)
    bulk_p50 = statistics.median(bulk_latencies_ms)
    print(
        f"REAL_TIME state p50 {state_p50:.2f} ms, max {max(state_latencies_ms):.2f} ms;"
        f" bulk p50 {bulk_p50:.1f} ms"
    )
    assert bulk_p50 > 100, "the default link was not congested, so the test shows nothing"
    assert state_p50 < 20
    assert max(state_latencies_ms) < bulk_p50 / 4


def test_drone_config_uses_peer_mode_no_listeners_no_scouting() -> None:
    zcfg = _Json(session_config(ZenohConfig(), Role.DRONE))
    assert zcfg.get_json("mode") == "peer"
    assert zcfg.get_json("listen/endpoints") == []
    assert zcfg.get_json("scouting/multicast/enabled") is False
    assert zcfg.get_json("scouting/gossip/enabled") is False
    assert zcfg.get_json("transport/unicast/max_links") >= 2
    assert zcfg.get_json("transport/shared_memory/enabled") is False
    connect = zcfg.get_json("connect/endpoints")
    assert connect == ["tcp/127.0.0.1:7447?prio=4-7#so_sndbuf=65536", "tcp/127.0.0.1:7448?prio=1-3#dscp=0xb8"]
    edge = _Json(session_config(ZenohConfig(edge_host="::1"), Role.EDGE))
    assert edge.get_json("mode") == "client"
    assert edge.get_json("connect/endpoints") == ["tcp/[::1]:7447"]


class _Json:
    def __init__(self, zcfg: zenoh.Config) -> None:
        self.zcfg = zcfg

    def get_json(self, key: str) -> Any:
        return json.loads(self.zcfg.get_json(key))


def test_unreachable_router_gives_a_transport_error() -> None:
    cfg = ZenohConfig(**flow_ports(), connect_timeout_s=0.3)
    with pytest.raises(TransportError, match="cannot open zenoh drone session"):
        open_bus(cfg, Role.DRONE)


class _HungSession:
    """A session whose close waits on a peer that never answers (the router hang seen once in CI)."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def close(self) -> None:
        self.release.wait(30.0)


def test_a_hung_session_close_is_bounded_and_reported(caplog: pytest.LogCaptureFixture) -> None:
    session = _HungSession()
    try:
        assert close_session(session, "router", within_s=0.2) is False
    finally:
        session.release.set()
    assert "router: zenoh session close did not finish" in caplog.text


def test_a_real_session_closes_within_the_bound() -> None:
    session = zenoh.open(
        zenoh.Config.from_json5(
            '{"mode": "peer", "listen": {"endpoints": []}, "scouting": {"multicast": {"enabled": false}}}'
        )
    )
    assert close_session(session, "peer") is True
