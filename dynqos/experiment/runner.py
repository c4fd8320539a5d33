"""Run one scenario end to end on one machine: the paper's experiment, as real processes.

Start the router, the cell emulator, the simulator, the planner, the MPC, the detector and the onboard
daemon with the scenario's config (free ports on 127.0.0.1); wait until the drone offloads; fly for
`duration_s`, switching the cell's background load on at `bg_start_s` through the cell's control API
and injecting the scenario's faults; record what a ground station would see (dynqos/experiment/recording.py);
stop every process (also on Ctrl-C or when any of them dies, naming it); write the run folder
(dynqos/reports/summary.py).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from dynqos.common.config import Config, ZenohConfig
from dynqos.common.transport import Role, open_bus
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.flight import (
    Streams,
    fly,
    fly_and_stop,
    post_json,
    start_mcap_recorder,
    start_replicas,
    wait_for_offload,
)
from dynqos.experiment.processes import Processes, flow_ports, free_port, free_udp_block
from dynqos.experiment.recording import Recording
from dynqos.experiment.scenario import REPLICA_FAULTS, UAV, Scenario, scenario_config, with_cell, write_config
from dynqos.experiment.vehicles import (
    contacts,
    px4_config,
    px4_instances,
    px4_workdir,
    start_vehicle,
    track,
    with_px4_flight,
    world_of,
)
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
    config_path = folder / "dynqos.toml"
    write_config(config_path, scenario, config)
    procs = Processes(config_path, logs, scenario.metrics_port)
    rec = Recording()

    def fly() -> None:
        cell_port = _start_edge_and_cell(procs, scenario, config, config_path, folder, px4)
        _record_flight(scenario, config, procs, cell_port, rec, stop, progress)

    ok, failure = fly_and_stop(scenario, folder, procs, rec, fly, stop, progress)
    onboard_log = logs / "onboard.log"
    log_text = onboard_log.read_text(errors="replace") if onboard_log.exists() else ""
    summary = summarise(scenario, rec, log_text, ok=ok, failure=failure)
    summary["vehicle"] = scenario.vehicle
    if px4 is not None:
        with_px4_flight(summary, px4_workdir(folder, px4), scenario)
        summary["px4"]["contacts"] = contacts(world_of(config), track(rec))
    write_scenario(folder, scenario, rec, summary)
    return summary


def _start_edge_and_cell(
    procs: Processes, scenario: Scenario, config: Config, config_path: Path, folder: Path, px4: int | None
) -> int:
    """Everything but the drone, in dependency order; returns the cell's control port. The drone's flows
    connect to the bearer ports the cell reports and the QoS agent to its QoD API, so the config is
    written again once it is up. The agent stops before the cell (reverse order): the sessions it deletes
    on SIGTERM are gone from the cell's final qod.json."""
    procs.start("router", ["edge", "router"])
    cell = procs.start("cell", ["sim", "cell", "--out", str(folder)])
    sink_port = free_port() if scenario.qos_agents == 1 else 0
    write_config(config_path, scenario, with_cell(config, cell, sink_port=sink_port))
    with procs.together():  # each needs only the router, the cell and the config
        start_replicas(procs, "qos", scenario.qos_agents)
        start_mcap_recorder(procs, scenario, folder)
        start_vehicle(procs, folder, px4)
        start_replicas(procs, "planner", scenario.planner_replicas)
        start_replicas(procs, "mpc", scenario.mpc_replicas)
        procs.start("detector", ["edge", "detector"])
        if scenario.ros2_bridge:
            procs.start("ros2", ["edge", "ros2"])
    port: int = cell["control_port"]
    return port


def _record_flight(
    scenario: Scenario,
    config: Config,
    procs: Processes,
    cell_port: int,
    rec: Recording,
    stop: threading.Event,
    progress: bool,
) -> None:
    bus = open_bus(config.zenoh, Role.EDGE)
    uplink_mbps = config.cell.uplink_mbps
    try:
        streams = Streams.subscribe(bus)
        procs.start("onboard", ["onboard", "--takeoff"])
        rec.offload_ns = rec.t0_ns = wait_for_offload(streams.states, procs, stop)
        replica_faults = any(f.kind in REPLICA_FAULTS for f in scenario.faults)
        injector = FaultInjector(
            procs,
            lambda event: post_json(cell_port, "/events", event),
            bus,
            uplink_mbps=uplink_mbps,
            watch_uav=UAV if replica_faults else None,
        )
        try:
            fly(scenario, procs, cell_port, injector, rec, stop, progress)
        finally:
            injector.close()
            rec.faults = injector.windows
        streams.drain_into(rec)
    finally:
        bus.close()
