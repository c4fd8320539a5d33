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
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.config import Config, ZenohConfig
from dynqos.common.keys import Downlink
from dynqos.common.messages import QosDecision
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received, Role, endpoints, open_bus
from dynqos.experiment.faults import FaultInjector
from dynqos.experiment.flight import (
    QUEUE_ITEMS,
    Streams,
    fly,
    fly_and_stop,
    post_json,
    start_replicas,
    start_router_and_cell,
    wait_for_offload,
)
from dynqos.experiment.link_relay import LinkRelay
from dynqos.experiment.processes import Processes, flow_ports, free_port, free_udp_block
from dynqos.experiment.sites import (
    SiteFaults,
    operators_qod,
    site_b_config,
    site_configs,
    start_site_b,
    with_cell_b,
    with_site_b_bearers,
    with_two_paths,
)
from dynqos.experiment.vehicles import (
    contacts,
    px4_workdir,
    start_vehicle,
    track,
    with_px4_fleet,
    with_px4_flight,
    world_of,
)
from dynqos.plan.cells import with_cell
from dynqos.plan.offloaded import offloaded
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import REPLICA_FAULTS, Scenario, fleet_configs, write_config
from dynqos.reports.fleet import summarise_fleet, write_fleet
from dynqos.reports.mission import mission_figures, vehicle_tracks
from dynqos.reports.routes import plot_routes

log = logging.getLogger(__name__)

DETECTOR_NICE = 10


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

    def fly() -> None:
        site_b = None if shared_b is None else site_b_config(scenario, shared_b, folder)
        cell, cell_b = start_router_and_cell(procs, folder, site_b)
        sink_port = free_port() if scenario.qos_agents == 1 else 0  # several agents poll (scenario.py)
        write_config(shared_path, scenario, with_cell(shared, cell, sink_port=sink_port))
        cells = {"a": cell}
        if site_b is not None and shared_b is not None and cell_b is not None:
            path_b, cells["b"] = site_b[0], cell_b
            with_cell_b(path_b, scenario, shared_b, cell_b)
        for uav, config in drones.items():
            config = with_cell(config, cell)
            write_config(paths[uav], scenario, with_two_paths(config, cells) if shared_b else config)
        _start_edge(procs, scenario, shared, drones, paths, folder, px4)
        if shared_b is not None:
            start_site_b(procs, scenario, path_b)
        _record_fleet(
            scenario,
            (shared.zenoh, shared_b.zenoh if shared_b else None),
            procs,
            paths,
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


def _start_edge(
    procs: Processes,
    scenario: Scenario,
    shared: Config,
    drones: dict[str, Config],
    paths: dict[str, Path],
    folder: Path,
    px4: list[int] | None,
) -> None:
    """Every process but the router, the cell and the drones' daemons: the QoS agents, the vehicles, the
    planner and MPC replicas, the fleet planner, the detector (and the ROS 2 face)."""
    if px4:  # PX4 instances boot one at a time, as they always have
        _start_vehicles(procs, folder, drones, paths, px4)
    with procs.together():  # each needs only the router, the cell and the configs
        start_replicas(procs, "qos", scenario.qos_agents)
        # No MCAP recorder here: four drones already take this 2-core machine to its limit, and a fifth
        # subscriber of every state perturbed the fleet's figures in CI (docs/observability.md).
        if not px4:
            _start_vehicles(procs, folder, drones, paths, px4)
        start_replicas(procs, "planner", scenario.planner_replicas)
        start_replicas(procs, "mpc", scenario.mpc_replicas)
        nice = ["nice", "-n", str(DETECTOR_NICE), procs.exe]
        if shared.fleet_plan.tasks:  # it waits until every drone offloads, then plans and sends the legs
            # below the control path, as the detector: its planning is a burst of CPU, not a deadline
            procs.start("fleet-planner", ["edge", "fleet-planner"], program=nice)
        # The detector is best effort (it drops the frames it cannot keep up with): on one machine it
        # runs below the control path, as it would on its own cores at a real edge.
        procs.start("detector", ["edge", "detector"], program=nice)
        for task in offloaded(scenario.tasks):  # the user's own tasks, each its own service
            procs.start(task.process, ["edge", "serve", task.edge])
        if scenario.ros2_bridge:  # best effort as well
            procs.start("ros2", ["edge", "ros2"], program=nice)


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


def _start_vehicles(
    procs: Processes, folder: Path, drones: dict[str, Config], paths: dict[str, Path], px4: list[int] | None
) -> None:
    """Each drone's vehicle, where its config stands it: dynqos's vehicle `--instance i`, or PX4."""
    for i, (uav, config) in enumerate(drones.items()):
        start_vehicle(
            procs,
            folder,
            px4[i] if px4 else None,
            name=f"vehicle-{uav}",
            instance=i,
            start_m=config.vehicle.start_m,
            config=paths[uav],
        )


def cell_event(port: int) -> Callable[[dict[str, Any]], object]:
    return lambda event: post_json(port, "/events", event)


def _read(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def _record_fleet(
    scenario: Scenario,
    zenohs: tuple[ZenohConfig, ZenohConfig | None],
    procs: Processes,
    paths: dict[str, Path],
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
    connect = [endpoints(z, Role.EDGE)[0][0] for z in zenohs if z is not None]
    bus = open_bus(zenohs[0], Role.EDGE, connect=connect)
    try:
        streams = {uav: Streams.subscribe(bus, uav) for uav in paths}
        heard: BoundedQueue[Received] = BoundedQueue(QUEUE_ITEMS)
        bus.subscribe(keys.downlink_all_drones(Downlink.QOS_DECISION), heard, expect=(QosDecision,))
        # One drone at a time takes off and starts offloading: four take-offs at once on two cores
        # are a start-up no fleet flies, and their latencies would be the baseline's.
        # They stop at once (a PX4 drone lands before its daemon exits: about 8 s each).
        first = f"onboard-{next(iter(paths))}"
        for uav, path in paths.items():
            name = f"onboard-{uav}"
            procs.start(
                name, ["onboard", "--takeoff"], config=path, stop_with=None if name == first else first
            )
            recs[uav].offload_ns = wait_for_offload(streams[uav].states, procs, stop, f"onboard-{uav}")
        # The flight's time zero is when the last drone offloads: from then on every drone is recorded.
        rec.t0_ns = rec.offload_ns = time.monotonic_ns()
        # a replica fault acts on the replica serving the first drone (the others' may be another)
        watched = next(iter(paths)) if any(f.kind in REPLICA_FAULTS for f in scenario.faults) else None
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
