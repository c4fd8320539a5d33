"""A QoS agent per edge site, each asking its own operator (docs/multipath.md): two `dynqos edge qos`
processes in sites a and b on one router (as two linked routers make it), each with its own emulated
operator (`dynqos sim cell`), and a test drone on two paths asking each site for its own path. Each
agent serves only its site's requests and is active in its own site; a killed agent's session is taken
over by its restart (adopted, or deleted and created again: never two at once); none is left at either
operator at the end."""

from __future__ import annotations

import contextlib
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.messages import QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.common.transport import Role, open_bus
from tests.conftest import flow_ports, free_tcp_port
from tests.procs import DynqosProcess
from tests.test_qos_agent import UAV, Drone, Rig, write_config

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

SITES = ("a", "b")


@dataclass
class Sites:
    zenoh: ZenohConfig
    configs: dict[str, Path]
    operators: dict[str, Rig]  # each site's operator: its cell's counters and sessions
    procs: dict[str, DynqosProcess] = field(default_factory=dict)

    def agent(self, site: str) -> DynqosProcess:
        args = ["edge", "qos", "--set", f'qos.replica_id="qos-{site}"', "--set", f'qos.site="{site}"']
        return DynqosProcess(args, self.configs[site])

    def actives(self, site: str) -> list[str]:
        bus = open_bus(self.zenoh, Role.EDGE)
        try:
            return sorted(
                keys.replica_of_token(k) for k in bus.alive_tokens(keys.qos_actives(f"site-{site}-all"), 5)
            )
        finally:
            bus.close()

    def session_ids(self, site: str) -> list[str]:
        return [s["sessionId"] for s in self.operators[site].sessions()]


@contextlib.contextmanager
def two_sites(tmp_path: Path) -> Iterator[Sites]:
    zcfg = ZenohConfig(**flow_ports())
    configs, operators = {}, {}
    for site in SITES:
        port = free_tcp_port()
        configs[site] = tmp_path / f"site-{site}.toml"
        write_config(configs[site], zcfg, port, "camara")
        operators[site] = Rig(configs[site], zcfg, port, {})
    sites = Sites(zcfg, configs, operators)
    try:
        sites.procs["router"] = DynqosProcess(["edge", "router"], configs["a"])
        for site in SITES:
            sites.procs[f"cell-{site}"] = DynqosProcess(["sim", "cell"], configs[site])
        for site in SITES:
            sites.procs[f"qos-{site}"] = sites.agent(site)
        yield sites
    finally:
        for proc in reversed(list(sites.procs.values())):
            proc.stop()


class TwoPathDrone(Drone):
    """Asks each site's agent for its own path, as the onboard daemon does on two paths, and keeps
    each site's last grant."""

    def __init__(self, zcfg: ZenohConfig) -> None:
        super().__init__(zcfg)
        self.by_site: dict[str, QosGrant] = {}

    def ask_sites(self, want: dict[str, bool]) -> None:
        for site, wanted in want.items():
            self.seq += 1
            self.pub.put(
                QosRequest(uav=UAV, seq=self.seq, stamp_ns=time.monotonic_ns(), want=wanted, site=site)
            )

    def until_sites(self, want: dict[str, bool], grants: dict[str, Grant], check: Any = None) -> None:
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:
            self.ask_sites(want)
            item = self.grants.get(0.2)
            while item is not None:
                assert isinstance(item.message, QosGrant)
                self.by_site[item.message.site] = item.message
                item = self.grants.get_nowait()
            if all(site in self.by_site and self.by_site[site].grant is g for site, g in grants.items()) and (
                check is None or check()
            ):
                return
        raise AssertionError(f"not {grants} within 15 s: {self.by_site}")


def test_each_site_has_its_own_active_agent_asking_its_own_operator_and_none_is_left(tmp_path: Path) -> None:
    with two_sites(tmp_path) as sites:
        drone = TwoPathDrone(sites.zenoh)
        try:
            assert sites.actives("a") == ["qos-a"]  # each site's one agent is its site's active one
            assert sites.actives("b") == ["qos-b"]
            # path a wants priority, path b not: only operator A is asked
            drone.until_sites({"a": True, "b": False}, {"a": Grant.AVAILABLE, "b": Grant.NONE})
            assert len(sites.session_ids("a")) == 1
            assert sites.session_ids("b") == []
            assert set(drone.by_site) == {"a", "b"}  # each grant names its agent's site
            # both paths want it: each operator holds one session for the drone
            drone.until_sites({"a": True, "b": True}, {"a": Grant.AVAILABLE, "b": Grant.AVAILABLE})
            (session_a,) = sites.session_ids("a")
            assert len(sites.session_ids("b")) == 1
            # site a's agent dies with its session held: the operator keeps it until the agent's restart
            sites.procs["qos-a"].proc.send_signal(signal.SIGKILL)
            sites.procs["qos-a"].proc.wait(10)
            sites.procs["qos-a"].stop()  # (its output read and closed)
            assert sites.session_ids("a") == [session_a]
            sites.procs["qos-a"] = sites.agent("a")
            drone.until_sites(
                {"a": True, "b": True},
                {"a": Grant.AVAILABLE, "b": Grant.AVAILABLE},
                check=lambda: sites.actives("a") == ["qos-a"],
            )
            # the restart adopted the session (it had heard the drone by then) or deleted it as left by an
            # earlier agent and created one: never two at once
            assert len(sites.session_ids("a")) == 1
            assert sites.operators["a"].counters()["qod"]["conflicts"] == 0
        finally:
            drone.close()
        for site in SITES:  # SIGTERM: each agent deletes what it holds at its own operator
            sites.procs[f"qos-{site}"].stop()
        for site in SITES:
            assert sites.session_ids(site) == []
            qod = sites.operators[site].counters()["qod"]
            assert qod["deleted"] == qod["created"] >= 1, qod
        assert sites.operators["b"].counters()["qod"]["created"] == 1  # site b's agent lived throughout
