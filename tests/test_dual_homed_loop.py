"""A drone on two paths to two edge sites, as real processes on 127.0.0.1 (docs/multipath.md).

Site A and site B each run a router, an MPC replica and a planner; the routers are linked. The onboard
daemon holds one session per path (path a to A's router, path b to B's) and flies the simulator's
vehicle. Both sites answer every State; the drone flies the first answer. Then every process of site A
is SIGKILLed at once, the router the drone's path a dials among them: the drone flies on on site B's
Commands, without its fallback and without a gap between Commands as long as its watchdog."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Stream
from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import ControlSource
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received, Role, open_bus
from tests.conftest import flow_ports
from tests.procs import DynqosProcess
from tests.test_onboard_loop import loop_config

pytestmark = [pytest.mark.integration]

T_WD_MS = 150.0


def _site_configs(tmp_path: Path) -> tuple[Path, Path, Path, ZenohConfig]:
    """Site A's, site B's (its router linked to A's) and the drone's config (a path to each router)."""
    za, zb = ZenohConfig(**flow_ports()), ZenohConfig(**flow_ports())
    base = loop_config(tmp_path, za, extra='[mpc]\nsite = "a"\nhealth_interval_s = 1\n').read_text()
    site_a = tmp_path / "site-a.toml"
    site_a.write_text(base)
    site_b = tmp_path / "site-b.toml"
    site_b.write_text(
        base.replace(f"default_port = {za.default_port}", f"default_port = {zb.default_port}")
        .replace(f"priority_port = {za.priority_port}", f"priority_port = {zb.priority_port}")
        .replace('site = "a"', 'site = "b"')
        .replace("[zenoh]\n", f'[zenoh]\nrouter_links = ["tcp/127.0.0.1:{za.default_port}"]\n')
    )
    drone = tmp_path / "drone.toml"
    drone.write_text(
        base
        + "".join(
            f'[[onboard.paths]]\nname = "{name}"\nconnect_default = "127.0.0.1:{z.default_port}"\n'
            f'connect_priority = "127.0.0.1:{z.priority_port}"\n'
            for name, z in (("a", za), ("b", zb))
        )
    )
    return site_a, site_b, drone, zb


def _statuses(queue: BoundedQueue[Received], seen: dict[int, SupervisorStatus]) -> None:
    for item in queue.drain():  # by both paths: each status arrives twice
        if isinstance(item.message, SupervisorStatus):
            seen.setdefault(item.message.seq, item.message)


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_a_dual_homed_drone_flies_on_through_the_loss_of_a_whole_site(tmp_path: Path) -> None:
    site_a, site_b, drone, zb = _site_configs(tmp_path)
    procs: dict[str, DynqosProcess] = {}
    killed: list[DynqosProcess] = []
    seen: dict[int, SupervisorStatus] = {}
    bus = None
    log = ""
    try:
        procs["router-a"] = DynqosProcess(["edge", "router"], site_a)
        procs["router-b"] = DynqosProcess(["edge", "router"], site_b)
        procs["vehicle"] = DynqosProcess(["sim", "vehicle", "--duration", "300"], site_a)
        for site, config in (("a", site_a), ("b", site_b)):
            env = {"DYNQOS_MPC__REPLICA_ID": f"mpc-{site}", "DYNQOS_PLANNER__REPLICA_ID": f"planner-{site}"}
            procs[f"planner-{site}"] = DynqosProcess(["edge", "planner"], config, env=env)
            procs[f"mpc-{site}"] = DynqosProcess(["edge", "mpc"], config, env=env)
        bus = open_bus(zb, Role.EDGE)  # a ground station at site B: it outlives site A
        queue: BoundedQueue[Received] = BoundedQueue(100_000)
        bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATUS), queue, expect=(SupervisorStatus,))
        procs["onboard"] = DynqosProcess(["onboard", "--takeoff"], drone)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # flying on the edge, answered by both sites by both paths
            time.sleep(0.5)
            _statuses(queue, seen)
            last = seen[max(seen)] if seen else None
            if last and last.control_source is ControlSource.EDGE and last.duplicates > 100:
                break
        else:
            raise AssertionError(f"never flew from both sites: {procs['onboard'].stop()[-3000:]}")
        before = seen[max(seen)]
        time.sleep(2.0)  # both sites fly a while
        for name in ("router-a", "mpc-a", "planner-a"):  # site A goes, all at once
            killed.append(procs.pop(name))
            killed[-1].proc.kill()
        time.sleep(6.0)
        _statuses(queue, seen)
        log = procs.pop("onboard").stop()
    finally:
        if bus is not None:
            bus.close()
        for proc in [*reversed(procs.values()), *killed]:
            proc.stop()
    after = [s for seq, s in sorted(seen.items()) if seq > before.seq]
    assert after, log[-3000:]
    assert {s.control_source for s in after} == {ControlSource.EDGE}, log[-3000:]
    assert after[-1].fallbacks == before.fallbacks, log[-3000:]
    assert after[-1].site == "b"  # site A is gone: site B's Commands fly the drone
    assert after[-1].camera_path == "b"  # and the camera left the path whose router is gone
    rtts = dict(after[-1].path_rtt_samples_ms)
    assert rtts["b"], rtts  # path b still answers,
    assert not rtts["a"], rtts  # path a has nothing left to carry
    health = re.findall(r"max_command_gap_ms=([0-9.]+)", log)
    assert health, log[-3000:]
    assert float(health[-1]) < T_WD_MS, log[-3000:]
    assert "first command from site b" in log
    print(log[log.rfind("onboard health") :][:800])
