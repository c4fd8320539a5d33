"""MPC replicas at two edge sites, each with its own router, the routers linked (`[zenoh] router_links`):
they share the drones as replicas on one router do, and when one site goes (its router killed), the
other site's replica takes its drones without a gap a drone would notice. Real processes on 127.0.0.1."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import Command, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received, Role, open_bus
from dynqos.edge.replicas import ranked
from tests.conftest import flow_ports
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

T_WD_NS = 150_000_000  # the drone's watchdog: a longer gap between commands would send it to its fallback
PERIOD_NS = 50_000_000  # the drones' states, 20 Hz
REPLICAS = ("mpc-a", "mpc-b")


def _site(tmp_path: Path, name: str, links: list[str]) -> tuple[Path, ZenohConfig]:
    zcfg = ZenohConfig(**flow_ports())
    config = tmp_path / f"{name}.toml"
    config.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        f"router_links = {links!r}\n".replace("'", '"')
        + "[mpc]\nhealth_interval_s = 1\n[planner]\nlead_in_s = 1\nhealth_interval_s = 1\n"
    )
    return config, zcfg


def _fly(zcfg: ZenohConfig, uavs: list[str], seconds: float, at_s: float, action: Callable[[], None]
         ) -> tuple[dict[str, list[tuple[int, Command]]], list[int]]:  # fmt: skip
    """20 Hz states for each drone (announced, as its daemon does) for `seconds`; `action` at `at_s`.
    Returns each drone's commands with their arrival times, and when each round of states was sent."""
    bus = open_bus(zcfg, Role.DRONE)
    got: dict[str, list[tuple[int, Command]]] = {uav: [] for uav in uavs}
    sent: list[int] = []
    try:
        queue: BoundedQueue[Received] = BoundedQueue(10_000)
        tokens = [bus.declare_token(keys.drone_presence(uav)) for uav in uavs]  # held until the end
        for uav in uavs:
            bus.subscribe(keys.downlink(uav, Downlink.COMMAND), queue, expect=(Command,))
        pubs = {uav: bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME,
                                   express=True) for uav in uavs}  # fmt: skip
        assert all(pub.wait_matched(20) for pub in pubs.values()), "no MPC followed the drones"
        start, seq, acted = time.monotonic(), 0, False
        while (now := time.monotonic()) - start < seconds:
            if not acted and now - start >= at_s:
                action()
                acted = True
            seq += 1
            sent.append(time.monotonic_ns())
            for uav, pub in pubs.items():
                pub.put(State(uav=uav, seq=seq, stamp_ns=time.monotonic_ns(), pos_m=(0.0, 0.0, -1.5),
                              vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0)))  # fmt: skip
            end = now + 0.05  # 20 Hz states; what came back meanwhile
            while (item := queue.get(max(0.0, end - time.monotonic()))) is not None:
                assert isinstance(item.message, Command)
                got[item.message.uav].append((item.arrival_ns, item.message))
        del tokens
    finally:
        bus.close()
    return got, sent


def _own_stall_ns(sent: list[int], start_ns: int, end_ns: int) -> int:
    """The time within (start, end) that the edge had no state to answer because this process (the
    drones) was descheduled: each pause of over two periods between rounds of states, less the period
    it would have waited anyway. A round's usual lateness counts for nothing."""
    stalled = 0
    for a, b in itertools.pairwise(sent):
        overlap = min(b, end_ns) - max(a, start_ns)
        if overlap > 2 * PERIOD_NS:
            stalled += overlap - PERIOD_NS
    return stalled


def test_replicas_at_two_linked_sites_share_the_drones_and_survive_the_loss_of_one_site(
    tmp_path: Path,
) -> None:
    config_a, zcfg_a = _site(tmp_path, "site-a", [])
    config_b, _ = _site(tmp_path, "site-b", [f"tcp/127.0.0.1:{zcfg_a.default_port}"])
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router-a"] = DynqosProcess(["edge", "router"], config_a)
        procs["router-b"] = DynqosProcess(["edge", "router"], config_b)
        procs["planner"] = DynqosProcess(["edge", "planner"], config_a)
        for name, config in zip(REPLICAS, (config_a, config_b), strict=True):
            procs[name] = DynqosProcess(["edge", "mpc"], config, env={"DYNQOS_MPC__REPLICA_ID": name})
        uavs = [f"uav{i}" for i in range(1, 7)]
        at_b = [uav for uav in uavs if ranked(uav, REPLICAS)[0] == "mpc-b"]
        assert at_b, "six drones: each site ranks first for some"
        assert len(at_b) < len(uavs), "six drones: each site ranks first for some"
        got, sent = _fly(zcfg_a, uavs, seconds=8.0, at_s=4.0, action=procs["router-b"].proc.kill)
        logs = {name: procs.pop(name).stop() for name in ("mpc-a", "mpc-b")}
    finally:
        for proc in reversed(procs.values()):
            proc.stop()
    assert "replica mpc-b joined" in logs["mpc-a"], logs["mpc-a"][-2000:]
    assert "replica mpc-b left" in logs["mpc-a"], logs["mpc-a"][-2000:]
    for uav, commands in got.items():
        flyers = [c.replica for _, c in commands]
        assert flyers, f"{uav}: no command; mpc-a: {logs['mpc-a'][-3000:]}\nmpc-b: {logs['mpc-b'][-3000:]}"
        assert flyers[-1] == "mpc-a", uav  # site B is gone: site A flies every drone
        if uav in at_b:
            assert "mpc-b" in flyers, f"{uav}: site B's replica never flew it"  # across the link
        times = [t for t, _ in commands][len(commands) // 4 :]  # past the start-up, across the loss
        gaps = [(b - a - _own_stall_ns(sent, a, b), b - a) for a, b in itertools.pairwise(times)]
        longest, raw = max(gaps)
        print(
            f"{uav}: {len(commands)} commands, by {sorted(set(flyers))}, longest gap {longest / 1e6:.0f} ms"
            f" ({raw / 1e6:.0f} ms with the drones' own stalls)"
        )
        assert longest < T_WD_NS, f"{uav}: a {longest / 1e6:.0f} ms gap would have sent it to its fallback"
