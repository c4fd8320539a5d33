"""Who flies a scenario's drone: dynqos's simulated vehicle (`dynqos sim vehicle`) or a real PX4 SITL
(`dynqos sim px4`, sim/vehicle/px4_sitl.py). Either is the process named "vehicle" in the run, so faults
and logs find it the same way; what differs is where the onboard daemon listens. PX4 keeps its own
ports, so the daemon listens where PX4 instance N sends (14540+N) and reads system id N+1."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from dynqos.common.config import Config
from dynqos.plan.flight import SHARED
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import Scenario
from dynqos.sim.vehicle.world import World, collision, default_world, load_world

Vec3 = tuple[float, float, float]


def px4_config(config: Config, instance: int) -> Config:
    """`config` for a drone flown by PX4 instance `instance`: the daemon on PX4's offboard link, reading
    PX4's events with the build's catalogue, and the radio map (if on) hearing PX4's ground-station
    link."""
    from dynqos.sim.vehicle.px4_sitl import Px4Ports, event_catalogue, px4_folder

    ports = Px4Ports(instance)
    events = event_catalogue(px4_folder(config.px4.dir))
    onboard = replace(
        config.onboard,
        mavlink_url=f"udpin:127.0.0.1:{ports.offboard_remote}",
        fc_system_id=ports.system_id,
        px4_events=str(events) if events else config.onboard.px4_events,
        on_exit="land",  # the flight ends as PX4 expects: landed and disarmed before PX4 stops
    )
    return px4_radio(replace(config, onboard=onboard))


def px4_radio(config: Config) -> Config:
    """The radio map (if on) hears the vehicles where every PX4 instance sends its ground-station link:
    14550 (PX4's own port)."""
    from dynqos.sim.vehicle.px4_sitl import Px4Ports

    if not config.cell.radio.enabled:
        return config
    radio = replace(config.cell.radio, position_port=Px4Ports(0).gcs_remote)
    return replace(config, cell=replace(config.cell, radio=radio))


def with_px4(configs: dict[str, Config], drones: Sequence[str], px4: list[int] | None) -> dict[str, Config]:
    """A flight's configs (keyed as its plan names them, dynqos/plan/flight.py) for PX4: the drone whose
    config is `drones[i]` flown by instance px4[i] (one drone's is the run's own), the radio map hearing
    PX4's ground-station link. As they are when dynqos's vehicles fly (`px4` None)."""
    if px4 is None:
        return configs
    configs = {**configs, SHARED: px4_radio(configs[SHARED])}
    for key, instance in zip(drones, px4, strict=True):
        configs[key] = px4_config(configs[key], instance)
    return configs


def px4_instances(scenario: Scenario) -> list[int] | None:
    """A free PX4 instance number for each of the scenario's drones (None: dynqos's vehicle flies)."""
    if scenario.vehicle != "px4":
        return None
    from dynqos.sim.vehicle.px4_sitl import free_instances

    return free_instances(len(scenario.uavs))


def with_px4_flight(
    summary: dict[str, Any], workdir: Path, scenario: Scenario, uav: str | None = None
) -> None:
    """`summary` (a fleet's: drone `uav`'s entry) with what PX4 did (its ULog, dynqos/reports/px4_log.py);
    a flight PX4 did not fly in offboard mode throughout, or one in which PX4's failsafe fired, is not ok
    (docs/px4.md)."""
    from dynqos.reports.px4_log import px4_report

    report = px4_report(workdir, scenario.duration_s)
    (summary if uav is None else summary["drones"][uav])["px4"] = report
    if not summary["ok"]:
        return
    who = f"{uav}: " if uav else ""
    if "error" in report:
        summary["ok"], summary["failure"] = False, f"{who}PX4's ULog: {report['error']}"
    elif not report["offboard_whole_flight"]:
        summary["ok"], summary["failure"] = False, f"{who}PX4 did not fly the whole flight in OFFBOARD"
    elif report["failsafes"]:
        summary["ok"], summary["failure"] = False, f"{who}PX4's failsafe fired: {report['failsafes'][0]}"


def contacts(world: World, track: Sequence[tuple[float, Vec3]]) -> list[dict[str, Any]]:
    """Each contact of the drone with the world along its `track` ((seconds, position) in the world's
    frame): what PX4 cannot report, since its world has no obstacles. The same sphere and rule as dynqos's
    vehicle checks in flight (sim/vehicle/world.py); one entry when a contact begins."""
    found, touching = [], None
    for t, pos in track:
        now = collision(world, pos) if pos[2] < -0.05 else None  # on the ground it touches nothing
        if now is not None and now != touching:
            found.append({"t_s": round(t, 2), "with": now, "at_m": [round(v, 2) for v in pos]})
        touching = now
    return found


def track(rec: Recording) -> list[tuple[float, Vec3]]:
    """The drone's positions as its states reported them, by seconds into the recorded flight."""
    return [((st.stamp_ns - (rec.t0_ns or 0)) / 1e9, st.pos_m) for _, st in rec.states]


def world_of(config: Config) -> World:
    """The world the drone's camera renders: `[onboard] world_file`, or the default arena."""
    return load_world(config.onboard.world_file) if config.onboard.world_file else default_world()
