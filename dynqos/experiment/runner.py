"""Run one scenario end to end on one machine: the paper's experiment, as real processes.

Start the router, the cell emulator, the simulator, the planner, the MPC, the detector and the onboard
daemon with the scenario's config (free ports on 127.0.0.1); wait until the drone offloads; fly for
`duration_s`, switching the cell's background load on at `bg_start_s` through the cell's control API
and injecting the scenario's faults; record what a ground station would see (dynqos/plan/recording.py);
stop every process (also on Ctrl-C or when any of them dies, naming it); write the run folder
(dynqos/reports/summary.py).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from dynqos.common.config import Config, ZenohConfig
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.flight import (
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
    with_two_paths,
)
from dynqos.experiment.vehicles import (
    contacts,
    px4_config,
    px4_instances,
    px4_workdir,
    track,
    with_px4_flight,
    world_of,
)
from dynqos.plan.cells import with_cell
from dynqos.plan.faults import SITE_FAULTS
from dynqos.plan.flight import SHARED, SITE_B, FlightPlan, plan_flight
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import REPLICA_FAULTS, UAV, Scenario, scenario_config, write_config
from dynqos.reports.multipath import fault_spans, path_figures
from dynqos.reports.summary import summarise, write_scenario

log = logging.getLogger(__name__)


def run_scenario(
    scenario: Scenario,
    out: Path,
    *,
    folder: Path | None = None,
    stop: threading.Event | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run one scenario into `folder` (default out/<run id>/) and return its summary."""
    if scenario.fleet:
        from dynqos.experiment.fleet import run_fleet

        return run_fleet(scenario, out, folder=folder, stop=stop, progress=progress)
    stop = stop or threading.Event()
    folder = folder or out / scenario.run_id
    logs = folder / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    udp = free_udp_block(2)  # the vehicle's offboard port, then the ground station's
    config = scenario_config(scenario, zenoh=ZenohConfig(**flow_ports()), fc_port=udp, gcs_port=udp + 1)
    instances = px4_instances(scenario)
    px4 = instances[0] if instances else None
    if px4 is not None:
        config = px4_config(config, px4)
    # a path_partition cuts the link between the sites' routers: it runs through a relay the runner owns
    partition = any(f.kind == "path_partition" for f in scenario.faults)
    relay = LinkRelay(config.zenoh.default_port) if partition else None
    config_b = None  # site B's, with two sites (docs/multipath.md)
    if scenario.sites == 2:
        link_port = relay.port if relay is not None else config.zenoh.default_port
        config, config_b = site_configs(config, ZenohConfig(**flow_ports()), link_port)
    config_path = folder / "dynqos.toml"
    write_config(config_path, scenario, config)
    procs = Processes(config_path, logs, scenario.metrics_port)
    rec = Recording()
    plan = plan_flight(scenario, folder, instances)
    configs = {SHARED: config_path, SITE_B: folder / "dynqos-b.toml"}

    def fly() -> None:
        cell_ports = _start_edge_and_cell(procs, scenario, plan, (config, config_b), configs, folder)
        _record_flight(
            scenario, plan, (config, config_b), procs, configs, cell_ports, rec, stop, progress, relay
        )

    try:
        ok, failure = fly_and_stop(scenario, folder, procs, rec, fly, stop, progress)
    finally:
        if relay is not None:
            relay.close()
    onboard_log = logs / "onboard.log"
    log_text = onboard_log.read_text(errors="replace") if onboard_log.exists() else ""
    summary = summarise(scenario, rec, log_text, ok=ok, failure=failure)
    summary["vehicle"] = scenario.vehicle
    if scenario.sites == 2 or any(f.kind in SITE_FAULTS for f in scenario.faults):
        summary["multipath"] = path_figures(rec.status, rec.t0_ns, *fault_spans(rec.faults))
    if scenario.sites == 2 and scenario.qos_backend == "camara":
        summary["qos_network"]["operators"] = operators_qod(folder)  # sessions at each site's operator
    if px4 is not None:
        with_px4_flight(summary, px4_workdir(folder, px4), scenario)
        summary["px4"]["contacts"] = contacts(world_of(config), track(rec))
    write_scenario(folder, scenario, rec, summary)
    return summary


def _start_edge_and_cell(
    procs: Processes,
    scenario: Scenario,
    plan: FlightPlan,
    config_pair: tuple[Config, Config | None],
    configs: dict[str, Path],
    folder: Path,
) -> dict[str, int]:
    """Everything but the drone, in the plan's order; returns each site's cell control port. The drone's
    flows connect to the bearer ports the cell reports and the QoS agent to its QoD API, so the config is
    written again once it is up. The agent stops before the cell (reverse order): the sessions it deletes
    on SIGTERM are gone from the cell's final qod.json. With two sites, site B's router, cell and
    services start from their own config (dynqos/experiment/sites.py)."""
    config, config_b = config_pair
    if config_b is not None:
        site_b_config(scenario, config_b, folder)
    cell, cell_b = start_network(procs, plan, configs)
    sink_port = free_port() if scenario.qos_agents == 1 else 0
    config = with_cell(config, cell, sink_port=sink_port)
    ports = {"a": int(cell["control_port"])}
    if config_b is not None and cell_b is not None:
        with_cell_b(configs[SITE_B], scenario, config_b, cell_b)
        config = with_two_paths(config, {"a": cell, "b": cell_b})
        ports["b"] = int(cell_b["control_port"])
    write_config(configs[SHARED], scenario, config)
    start_together(procs, plan.edge, configs)  # each needs only the routers, the cells and the configs
    for item in plan.after_edge:
        launch(procs, item, configs)
    return ports


def _record_flight(
    scenario: Scenario,
    plan: FlightPlan,
    config_pair: tuple[Config, Config | None],
    procs: Processes,
    configs: dict[str, Path],
    cell_ports: dict[str, int],
    rec: Recording,
    stop: threading.Event,
    progress: bool,
    relay: LinkRelay | None = None,
) -> None:
    config, config_b = config_pair
    bus = recorder_bus(config.zenoh, config_b.zenoh if config_b else None)  # as a ground station hears
    uplink_mbps = config.cell.uplink_mbps

    try:
        streams = Streams.subscribe(bus)
        launch(procs, plan.onboard[0], configs)
        rec.offload_ns = rec.t0_ns = wait_for_offload(streams.states, procs, stop)
        rec.cpu_s_t0 = procs.cpu_seconds()
        replica_faults = any(f.kind in REPLICA_FAULTS for f in scenario.faults)
        injector = FaultInjector(
            procs,
            cell_event(cell_ports["a"]),
            bus,
            uplink_mbps=uplink_mbps,
            watch_uav=UAV if replica_faults else None,
            sites=SiteFaults(procs, {site: cell_event(port) for site, port in cell_ports.items()}, relay),
        )
        try:
            more_cells = {site: port for site, port in cell_ports.items() if site != "a"}
            fly(scenario, procs, cell_ports["a"], injector, rec, stop, progress, more_cells)
        finally:
            injector.close()
            rec.faults = injector.windows
        streams.drain_into(rec)
    finally:
        bus.close()
