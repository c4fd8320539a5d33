"""Fly one scenario end to end on one machine, one drone or a fleet: the paper's experiment, as real
processes.

One function flies every scenario, and one drone is a fleet of one. The scenario becomes a plan
(dynqos/plan/flight.py) and its config files, then: the network, the vehicles and the edge start in
the plan's order (free ports on 127.0.0.1); each drone's daemon starts and is waited for until its drone
offloads; the flight lasts `duration_s`, with the load and the faults on the plan's timeline; the
recorder hears what a ground station would (dynqos/plan/recording.py); every process stops (also on
Ctrl-C or when any of them dies, naming it); the run folder is written (dynqos/reports/).
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.config import Config
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
from dynqos.experiment.flight_configs import config_paths, flight_configs, write_configs
from dynqos.experiment.flight_report import write_report
from dynqos.experiment.link_relay import LinkRelay
from dynqos.experiment.processes import Processes, free_port
from dynqos.experiment.sites import SiteFaults, with_site_b, with_two_paths
from dynqos.experiment.vehicles import px4_instances
from dynqos.plan.cells import with_cell
from dynqos.plan.flight import SHARED, SITE_B, FlightPlan, plan_flight, site_b_folder
from dynqos.plan.recording import FlightRecords
from dynqos.plan.scenario import REPLICA_FAULTS, Scenario


def run_scenario(
    scenario: Scenario,
    out: Path,
    *,
    folder: Path | None = None,
    stop: threading.Event | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Fly one scenario into `folder` (default out/<run id>/) and return its summary."""
    stop = stop or threading.Event()
    folder = folder or out / scenario.run_id
    (folder / "logs").mkdir(parents=True, exist_ok=True)
    px4 = px4_instances(scenario)  # None: dynqos's vehicles fly
    plan = plan_flight(scenario, folder, px4)
    configs = flight_configs(scenario, plan, folder, px4)
    # a path_partition cuts the link between the sites' routers: it runs through a relay the runner owns
    partition = any(f.kind == "path_partition" for f in scenario.faults)
    relay = LinkRelay(configs[SHARED].zenoh.default_port) if partition else None
    if scenario.sites == 2:  # site B's config beside the run's (docs/multipath.md)
        configs = with_site_b(configs, relay.port if relay is not None else 0)
        site_b_folder(folder).mkdir(exist_ok=True)
    paths = config_paths(folder, configs)
    write_configs(paths, scenario, configs)
    procs = Processes(paths[SHARED], folder / "logs", scenario.metrics_port)
    records = FlightRecords.of(plan.drones, fleet=scenario.fleet)

    def start_and_record() -> None:
        cells = _start(procs, scenario, plan, configs, paths)
        _record(scenario, plan, configs, paths, procs, cells, records, stop, progress, relay)

    try:
        ok, failure = fly_and_stop(scenario, folder, procs, records.flight, start_and_record, stop, progress)
    finally:
        if relay is not None:
            relay.close()
    return write_report(scenario, plan, folder, configs, records, px4, ok=ok, failure=failure)


def _start(
    procs: Processes,
    scenario: Scenario,
    plan: FlightPlan,
    configs: dict[str, Config],
    paths: dict[str, Path],
) -> dict[str, int]:
    """Everything but the drones' daemons, in the plan's order; each site's cell's control port. The
    drones' flows connect to the bearer ports each cell reports and the QoS agents to its QoD API, so
    the configs are written again once the cells are up. The agent stops before the cell (reverse
    order): the sessions it deletes on SIGTERM are gone from the cell's final qod.json."""
    cell, cell_b = start_network(procs, plan, paths)
    cells = {"a": cell} if cell_b is None else {"a": cell, "b": cell_b}
    sink_port = free_port() if scenario.qos_agents == 1 else 0  # several agents poll (scenario.py)
    configs[SHARED] = with_cell(configs[SHARED], cell, sink_port=sink_port)
    for key in plan.drone_configs():  # one drone's is the run's, with the cell already
        config = configs[key] if key == SHARED else with_cell(configs[key], cell)
        configs[key] = with_two_paths(config, cells) if cell_b is not None else config
    if cell_b is not None:
        configs[SITE_B] = with_cell(configs[SITE_B], cell_b)
    write_configs(paths, scenario, configs)
    for item in plan.vehicles:  # PX4 instances of a fleet boot one at a time
        launch(procs, item, paths)
    start_together(procs, plan.edge, paths)  # each needs only the routers, the cells and the configs
    for item in plan.after_edge:
        launch(procs, item, paths)
    return {site: int(c["control_port"]) for site, c in cells.items()}


def _record(
    scenario: Scenario,
    plan: FlightPlan,
    configs: dict[str, Config],
    paths: dict[str, Path],
    procs: Processes,
    cell_ports: dict[str, int],
    records: FlightRecords,
    stop: threading.Event,
    progress: bool,
    relay: LinkRelay | None,
) -> None:
    """Start every drone's daemon, one at a time, each waited for until its drone offloads; then fly
    the scenario. The recorder hears the drones as a ground station would: with two sites through
    either router, so that it hears on when one site is killed."""
    site_b = configs.get(SITE_B)
    bus = recorder_bus(configs[SHARED].zenoh, site_b.zenoh if site_b else None)
    rec = records.flight
    try:
        streams = {uav: Streams.subscribe(bus, uav) for uav in plan.drones}
        heard: BoundedQueue[Received] = BoundedQueue(QUEUE_ITEMS)
        bus.subscribe(keys.downlink_all_drones(Downlink.QOS_DECISION), heard, expect=(QosDecision,))
        # Four take-offs at once on two cores are a start-up no fleet flies, and their latencies would
        # be the baseline's. The drones stop at once (a PX4 drone lands before its daemon exits).
        first = plan.onboard[0].name
        for uav, item in zip(plan.drones, plan.onboard, strict=True):
            launch(procs, item, paths, stop_with=None if item.name == first else first)
            records.drones[uav].offload_ns = wait_for_offload(streams[uav].states, procs, stop, item.name)
        # The flight's time zero is when the last drone offloads: from then on every drone is recorded.
        rec.t0_ns = rec.offload_ns = max(r.offload_ns or 0 for r in records.drones.values())
        rec.cpu_s_t0 = procs.cpu_seconds()
        # a replica fault acts on the replica serving the first drone (the others' may be another)
        watched = plan.drones[0] if any(f.kind in REPLICA_FAULTS for f in scenario.faults) else None
        injector = FaultInjector(
            procs,
            cell_event(cell_ports["a"]),
            bus,
            uplink_mbps=configs[SHARED].cell.uplink_mbps,
            watch_uav=watched,
            sites=SiteFaults(procs, {site: cell_event(port) for site, port in cell_ports.items()}, relay),
        )
        try:
            more_cells = {site: port for site, port in cell_ports.items() if site != "a"}
            fly(scenario, procs, cell_ports["a"], injector, rec, stop, progress, more_cells)
        finally:
            injector.close()
            rec.faults = injector.windows
        for uav, heard_of_drone in streams.items():
            heard_of_drone.drain_into(records.drones[uav])
            records.on_flight_clock(uav)
        records.decisions += [i.message for i in heard.drain() if isinstance(i.message, QosDecision)]
    finally:
        bus.close()
