"""Run a fleet scenario end to end on one machine: several drones in one emulated cell (docs/fleet.md).

One router, cell, QoS agent, planner, MPC and detector serve every drone; each drone is a simulated
vehicle (`dynqos sim vehicle --instance i`, as PX4 SITL numbers a fleet) and an onboard daemon with its
own config file. The recorder hears every drone as a ground station would, and the QoS agent's
decisions; the summary holds each drone's figures under `drones` (dynqos/reports/fleet.py).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.config import Config, ZenohConfig
from dynqos.common.keys import Downlink
from dynqos.common.messages import QosDecision
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.flight import (
    QUEUE_ITEMS,
    Streams,
    cell_event,
    fly,
    fly_and_stop,
    launch,
    recorder_bus,
    start_network,
    start_together,
    wait_for_offload,
)
from dynqos.experiment.link_relay import LinkRelay
from dynqos.experiment.processes import Processes, flow_ports, free_port, free_udp_block
from dynqos.experiment.sites import (
    SiteFaults,
    operators_qod,
    site_b_config,
    site_configs,
    with_cell_b,
    with_site_b_bearers,
    with_two_paths,
)
from dynqos.experiment.vehicles import (
    contacts,
    px4_workdir,
    track,
    with_px4_fleet,
    with_px4_flight,
    world_of,
)
from dynqos.plan.cells import with_cell
from dynqos.plan.flight import SHARED, SITE_B, FlightPlan, plan_flight
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import REPLICA_FAULTS, Scenario, fleet_configs, write_config
from dynqos.reports.fleet import summarise_fleet, write_fleet
from dynqos.reports.mission import mission_figures, vehicle_tracks
from dynqos.reports.routes import plot_routes

log = logging.getLogger(__name__)


def run_fleet(
    scenario: Scenario,
    out: Path,
    *,
    folder: Path | None = None,
    stop: threading.Event | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run one fleet scenario into `folder` (default out/<run id>/) and return its summary."""
    stop = stop or threading.Event()
    folder = folder or out / scenario.run_id
    logs = folder / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    shared, drones, px4 = _configs(scenario, folder)  # px4: None, dynqos's vehicles fly
    shared, shared_b, relay = _sites(scenario, shared)
    shared_path = folder / "dynqos.toml"
    paths = {uav: folder / f"{uav}.toml" for uav in drones}
    write_config(shared_path, scenario, shared)
    for uav, config in drones.items():
        write_config(paths[uav], scenario, config)
    procs = Processes(shared_path, logs, scenario.metrics_port)
    rec = Recording()  # what the fleet shares: the cell, the load, memory and CPU
    recs = {uav: Recording() for uav in drones}
    decisions: list[QosDecision] = []
    flight = plan_flight(scenario, folder, px4)
    configs = {SHARED: shared_path, SITE_B: folder / "dynqos-b.toml", **paths}

    def fly() -> None:
        cells = _start(procs, scenario, flight, configs, (shared, shared_b), drones)
        _record_fleet(
            scenario,
            flight,
            (shared.zenoh, shared_b.zenoh if shared_b else None),
            procs,
            configs,
            {site: int(c["control_port"]) for site, c in cells.items()},
            rec,
            recs,
            decisions,
            stop,
            progress,
            shared.cell.uplink_mbps,
            relay,
        )

    try:
        ok, failure = fly_and_stop(scenario, folder, procs, rec, fly, stop, progress)
    finally:
        if relay is not None:
            relay.close()
    onboard_logs = {uav: _read(logs / f"onboard-{uav}.log") for uav in drones}
    summary = summarise_fleet(scenario, rec, recs, decisions, onboard_logs, ok=ok, failure=failure)
    summary["vehicle"] = scenario.vehicle
    if scenario.sites == 2 and scenario.qos_backend == "camara":
        summary["qos_network"] = {"operators": operators_qod(folder)}  # sessions at each site's operator
    for uav, instance in zip(drones, px4 or [], strict=False):  # what each PX4 did
        with_px4_flight(summary, px4_workdir(folder, instance), scenario, uav)
        summary["drones"][uav]["px4"]["contacts"] = contacts(world_of(drones[uav]), track(recs[uav]))
    if (folder / "plan.json").exists():  # a planned mission (docs/planning.md): what became of it
        plan = json.loads((folder / "plan.json").read_text())
        summary["mission"] = mission_figures(folder, plan, rec, recs, shared.supervisor.watchdog_s)
        plot_routes(folder, plan, shared, vehicle_tracks(folder / "radio.csv", rec))
        summary["checks"]["nothing_left_booked"] = not plan["release_failed"]
    write_fleet(folder, scenario, rec, recs, decisions, summary)
    return summary


def _start(
    procs: Processes,
    scenario: Scenario,
    flight: FlightPlan,
    configs: dict[str, Path],
    sites: tuple[Config, Config | None],
    drones: dict[str, Config],
) -> dict[str, dict[str, Any]]:
    """Everything but the drones' daemons, in the plan's order, each config written again with what the
    cells report once they are up; each site's cell's ready line."""
    shared, shared_b = sites
    folder = configs[SHARED].parent
    if shared_b is not None:
        site_b_config(scenario, shared_b, folder)
    cell, cell_b = start_network(procs, flight, configs)
    sink_port = free_port() if scenario.qos_agents == 1 else 0  # several agents poll (scenario.py)
    write_config(configs[SHARED], scenario, with_cell(shared, cell, sink_port=sink_port))
    cells = {"a": cell}
    if shared_b is not None and cell_b is not None:
        cells["b"] = cell_b
        with_cell_b(configs[SITE_B], scenario, shared_b, cell_b)
    for uav, config in drones.items():
        config = with_cell(config, cell)
        write_config(configs[uav], scenario, with_two_paths(config, cells) if shared_b else config)
    for item in flight.vehicles:  # PX4 instances boot one at a time, as they always have
        launch(procs, item, configs)
    start_together(procs, flight.edge, configs)  # each needs only the routers, the cells and the configs
    for item in flight.after_edge:
        launch(procs, item, configs)
    return cells


def _sites(scenario: Scenario, shared: Config) -> tuple[Config, Config | None, LinkRelay | None]:
    """With two sites (docs/multipath.md): site A's config and site B's, B's router linked to A's
    through a relay the runner can cut when a path_partition fault needs it, and cell B's bearers to
    B's router."""
    partition = any(f.kind == "path_partition" for f in scenario.faults)
    relay = LinkRelay(shared.zenoh.default_port) if partition else None
    if scenario.sites != 2:
        return shared, None, relay
    shared, shared_b = site_configs(shared, ZenohConfig(**flow_ports()), relay.port if relay else 0)
    return shared, with_site_b_bearers(shared_b, shared.zenoh), relay


def _configs(scenario: Scenario, folder: Path) -> tuple[Config, dict[str, Config], list[int] | None]:
    """The fleet's shared config and each drone's, on free ports; the PX4 instances that fly them (None:
    dynqos's vehicles); a planned mission's plan written into the run folder."""
    n = len(scenario.drones)
    udp = free_udp_block(n + 1)  # each drone's offboard port, then the ground station's
    shared, drones = fleet_configs(scenario, zenoh=ZenohConfig(**flow_ports()), fc_base=udp, gcs_port=udp + n)
    shared, drones, px4 = with_px4_fleet(scenario, shared, drones)
    if shared.fleet_plan.tasks:  # the fleet's plan: for these drones, into the run folder
        fleet_plan = replace(shared.fleet_plan, drones=tuple(drones), plan_file=str(folder / "plan.json"))
        shared = replace(shared, fleet_plan=fleet_plan)
    return shared, drones, px4


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def _record_fleet(
    scenario: Scenario,
    flight: FlightPlan,
    zenohs: tuple[ZenohConfig, ZenohConfig | None],
    procs: Processes,
    configs: dict[str, Path],
    cell_ports: dict[str, int],
    rec: Recording,
    recs: dict[str, Recording],
    decisions: list[QosDecision],
    stop: threading.Event,
    progress: bool,
    uplink_mbps: float,
    relay: LinkRelay | None = None,
) -> None:
    """Start every drone, wait until all of them offload, then fly the scenario. With two sites the
    recorder hears the drones through either router, so that it hears on when one site is killed."""
    bus = recorder_bus(*zenohs)
    try:
        streams = {uav: Streams.subscribe(bus, uav) for uav in flight.drones}
        heard: BoundedQueue[Received] = BoundedQueue(QUEUE_ITEMS)
        bus.subscribe(keys.downlink_all_drones(Downlink.QOS_DECISION), heard, expect=(QosDecision,))
        # One drone at a time takes off and starts offloading: four take-offs at once on two cores
        # are a start-up no fleet flies, and their latencies would be the baseline's.
        # They stop at once (a PX4 drone lands before its daemon exits: about 8 s each).
        first = flight.onboard[0].name
        for uav, item in zip(flight.drones, flight.onboard, strict=True):
            launch(procs, item, configs, stop_with=None if item.name == first else first)
            recs[uav].offload_ns = wait_for_offload(streams[uav].states, procs, stop, item.name)
        # The flight's time zero is when the last drone offloads: from then on every drone is recorded.
        rec.t0_ns = rec.offload_ns = time.monotonic_ns()
        # a replica fault acts on the replica serving the first drone (the others' may be another)
        watched = flight.drones[0] if any(f.kind in REPLICA_FAULTS for f in scenario.faults) else None
        injector = FaultInjector(
            procs,
            cell_event(cell_ports["a"]),
            bus,
            uplink_mbps=uplink_mbps,
            watch_uav=watched,
            sites=SiteFaults(procs, {site: cell_event(port) for site, port in cell_ports.items()}, relay),
        )
        try:
            more_cells = {site: port for site, port in cell_ports.items() if site != "a"}
            fly(scenario, procs, cell_ports["a"], injector, rec, stop, progress, more_cells)
        finally:
            injector.close()
            rec.faults = injector.windows
        for uav, s in streams.items():
            recs[uav].faults = injector.windows  # what each fault did is measured on every drone
            s.drain_into(recs[uav])
            recs[uav].t0_ns = rec.t0_ns
            recs[uav].bg_on_ns = rec.bg_on_ns
            recs[uav].states = [(lat, st) for lat, st in recs[uav].states if st.stamp_ns >= rec.t0_ns]
        decisions += [i.message for i in heard.drain() if isinstance(i.message, QosDecision)]
    finally:
        bus.close()
