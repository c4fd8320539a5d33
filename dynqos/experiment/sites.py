"""Two edge sites and two cells on one machine, for a drone on two paths (docs/multipath.md).

Site A is the run's usual processes (router, cell, QoS agent, planner, MPC, detector); site B is a
second set under the same names with `-b` after them (router-b, cell-b, ...), started from a config of
its own: its router on other ports and linked to site A's, its MPC replicas in site b, its own cell
(seeded apart, with its own timeline). The drone's path a goes through cell A to router A, its path b
through cell B to router B. The faults `site_kill` and `cell_outage` act on one site (`site`), the
background load on one cell, `path_partition` on the link between the sites' routers (relayed by the
runner, dynqos/experiment/link_relay.py, when a scenario has that fault).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.config import Config, OnboardPathConfig, ZenohConfig
from dynqos.experiment.link_relay import LinkRelay
from dynqos.experiment.processes import Processes, flow_ports
from dynqos.plan.faults import Fault, FaultWindow
from dynqos.plan.flight import SHARED, SITE_B, site_b_folder
from dynqos.reports.summary import qod_sessions

log = logging.getLogger(__name__)

SITES = ("a", "b")
# the processes of a site (one site's edge: what a site kill takes down at once); the cell is the
# operator's radio, not the site's, and the recorders are the ground station's
SITE_SERVICES = ("router", "qos", "planner", "mpc", "detector", "task")  # task-<name>: a user's task


def process_name(name: str, site: str) -> str:
    """Site A's processes keep the run's usual names; site B's have `-b` after them."""
    return name if site == "a" else f"{name}-{site}"


def site_processes(procs: Processes, site: str) -> list[str]:
    """The running processes of `site`'s edge, by the names they were started under."""
    return [
        name
        for name in procs.procs
        if name.split("-")[0] in SITE_SERVICES
        and name.endswith("-b") == (site == "b")
        and name not in procs.down
    ]


def site_configs(config: Config, zenoh_b: ZenohConfig, link_port: int = 0) -> tuple[Config, Config]:
    """Site A's config (its MPC and QoS agent in site a) and site B's: B's router on its own ports and
    linked to A's (at `link_port`: A's default port, or a relay to it the runner can cut), its MPC and QoS
    agent in site b (each agent asks its own site's operator: its cell's QoD API, set once the cell is
    up), its cell seeded apart from A's."""
    a = replace(config, mpc=replace(config.mpc, site="a"), qos=replace(config.qos, site="a"))
    z = replace(
        zenoh_b,
        router_links=(f"tcp/127.0.0.1:{link_port or config.zenoh.default_port}",),
        bulk_sndbuf_bytes=config.zenoh.bulk_sndbuf_bytes,
    )
    b = replace(
        config,
        zenoh=z,
        mpc=replace(config.mpc, site="b"),
        qos=replace(config.qos, site="b"),
        cell=replace(config.cell, seed=config.cell.seed + 1),
    )
    return a, b


def with_site_b_bearers(config_b: Config, zenoh_a: ZenohConfig) -> Config:
    """Cell B's bearers (a fleet's: a pair per drone) forwarded to site B's router: each named bearer
    set for site A's ports gets site B's instead (the drones' own bearers of one site are unnamed: the
    cell forwards them to its config's router)."""
    z = config_b.zenoh
    to_b = {zenoh_a.default_port: z.default_port, zenoh_a.priority_port: z.priority_port}
    bearers = []
    for bearer in config_b.cell.bearers:
        host, _, port = bearer.target.rpartition(":")
        bearers.append(replace(bearer, target=f"{host}:{to_b.get(int(port), int(port))}"))
    return replace(config_b, cell=replace(config_b.cell, bearers=tuple(bearers)))


def with_site_b(configs: dict[str, Config], link_port: int) -> dict[str, Config]:
    """A flight's configs (keyed as its plan names them, dynqos/plan/flight.py) with site B's beside the
    run's: `site_configs`, with cell B's bearers forwarded to site B's router."""
    a, b = site_configs(configs[SHARED], ZenohConfig(**flow_ports()), link_port)
    return {**configs, SHARED: a, SITE_B: with_site_b_bearers(b, a.zenoh)}


def with_two_paths(config: Config, cells: dict[str, dict[str, Any]]) -> Config:
    """The drone's paths once both cells are up: path a dials cell A's bearers, path b cell B's."""
    uav = config.drone.id
    paths = tuple(
        OnboardPathConfig(
            name=site,
            connect_default=f"127.0.0.1:{cell['bearers'][f'{uav}-default']['port']}",
            connect_priority=f"127.0.0.1:{cell['bearers'][f'{uav}-priority']['port']}",
        )
        for site, cell in cells.items()
    )
    onboard = replace(config.onboard, connect_default="", connect_priority="", paths=paths)
    return replace(config, onboard=onboard)


class SiteFaults:
    """`site_kill`: SIGKILL every process of a site's edge at once (its router among them), restart
    them after `duration_s`; `cell_outage`: the site's cell carries nothing for `duration_s` (the cell's
    coverage_loss, connections kept); `path_partition`: the link between the sites' routers cut for
    `duration_s` (`relay`); `background`: the site's cell's background user."""

    def __init__(
        self,
        procs: Processes,
        cell_events: dict[str, Callable[[dict[str, Any]], object]],
        relay: LinkRelay | None = None,
    ) -> None:
        self.procs = procs
        self.cell_events = cell_events
        self.relay = relay  # the link between the sites' routers, with a path_partition fault
        self._killed: dict[int, list[str]] = {}

    def begin(self, window: FaultWindow) -> None:
        fault = window.fault
        if fault.kind == "site_kill":
            names = site_processes(self.procs, fault.site)
            for name in names:
                self.procs.kill(name)
            self._killed[id(window)] = names
            window.notes.append(f"site {fault.site}: killed {', '.join(names)}")
        elif fault.kind == "cell_outage":
            self._cell(fault, {"kind": "coverage_loss", "duration_s": fault.duration_s})
        elif fault.kind == "path_partition" and self.relay is not None:
            cut = self.relay.cut()
            window.notes.append(f"the link between the sites' routers cut ({cut} connection(s))")
        elif fault.kind == "background":
            self._cell(fault, {"kind": "background", "user": "bg", "offered_mbps": fault.offered_mbps})

    def end(self, window: FaultWindow) -> None:
        fault = window.fault
        if fault.kind == "site_kill":
            names = self._killed.pop(id(window), [])
            routers = [n for n in names if n.split("-")[0] == "router"]
            for name in routers:  # first: the services connect to it
                self.procs.restart(name)
            with self.procs.together():  # then the site's services at once
                for name in names:
                    if name not in routers:
                        self.procs.restart(name)
        elif fault.kind == "path_partition" and self.relay is not None:
            self.relay.mend()
        elif fault.kind == "background":
            self._cell(fault, {"kind": "background", "user": "bg", "offered_mbps": 0.0})

    def _cell(self, fault: Fault, event: dict[str, Any]) -> None:
        self.cell_events[fault.site](event)


def operators_qod(folder: Path) -> dict[str, dict[str, int]]:
    """Each operator's QoD sessions once every process stopped (each cell's qod.json): site -> counts."""
    files = {"a": folder / "qod.json", "b": site_b_folder(folder) / "qod.json"}
    return {site: qod_sessions(json.loads(path.read_text())) for site, path in files.items() if path.exists()}
