"""`dynqos sim vehicle`: the simulated quadrotor (sim/vehicle/mavlink.py) as a process, numbered the way
PX4 SITL numbers a fleet's vehicles: instance N has MAVLink system id N+1 and its offboard and
ground-station ports + N (one ground station on 14550 sees every vehicle)."""

from __future__ import annotations

import logging

from dynqos.common import mavsign
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError
from dynqos.common.lifecycle import ready_line, stop_on_signals
from dynqos.sim.vehicle import MAX_INSTANCE
from dynqos.sim.vehicle.mavlink import Link, MavlinkVehicle
from dynqos.sim.vehicle.model import VehicleModel
from dynqos.sim.vehicle.serial_link import SerialLink
from dynqos.sim.vehicle.world import default_world, load_world

log = logging.getLogger(__name__)


def instance_port(port: int, instance: int) -> int:
    """PX4 SITL's port of vehicle `instance`: `port` + instance; 0 (any free port) stays 0."""
    if port and port + instance > 65535:
        raise DynqosError(f"--instance {instance}: port {port} + {instance} is past 65535")
    return port + instance if port else 0


def run(
    config: Config,
    *,
    instance: int = 0,
    world_file: str | None = None,
    lockstep: bool | None = None,
    speed: float | None = None,
    duration_s: float | None = None,
) -> int:
    """Fly until SIGTERM or `duration_s` simulated seconds; None takes the [vehicle] setting."""
    v = config.vehicle
    world_file = v.world_file if world_file is None else world_file
    world = load_world(world_file) if world_file else default_world()
    lockstep = v.lockstep if lockstep is None else lockstep
    speed = v.speed if speed is None else speed
    if not 0.01 <= speed <= 100:
        raise DynqosError(f"--speed must be in 0.01..100, got {speed}")
    if duration_s is not None and duration_s <= 0:
        raise DynqosError(f"--duration must be > 0, got {duration_s}")
    if not 0 <= instance <= MAX_INSTANCE:
        raise DynqosError(f"--instance must be in 0..{MAX_INSTANCE}, got {instance}")
    n = instance
    offboard: Link | SerialLink = Link(
        "offboard",
        (v.host, instance_port(v.offboard_bind_port, n)),
        (v.host, instance_port(v.offboard_remote_port, n)),
    )
    if v.offboard_serial:
        offboard = SerialLink(
            "offboard", v.offboard_serial, baud=v.serial_baud, flow_control=v.serial_flow_control
        )
    links = [offboard, Link("gcs", (v.host, instance_port(v.gcs_bind_port, n)), (v.host, v.gcs_remote_port))]
    key = mavsign.load_key(v.signing_key) if v.signing_key else None
    vehicle = MavlinkVehicle(
        VehicleModel(v), links, speed=speed, lockstep=lockstep, world=world, system_id=n + 1, signing_key=key
    )
    try:
        vehicle.open()
    except OSError as exc:
        where = (
            f"open {v.offboard_serial}"
            if v.offboard_serial
            else f"bind the vehicle's MAVLink ports on {v.host}"
        )
        raise DynqosError(f"cannot {where}: {exc.strerror}") from None

    def stop() -> None:
        vehicle.stopped = True

    stop_on_signals("vehicle", stop)
    ready_line(
        "vehicle",
        instance=n,
        system_id=n + 1,
        links={link.name: _described(link) for link in links},
        clock="lockstep" if lockstep else "realtime",
        world=world_file or "default",
        signing="on" if key is not None else "off",
    )
    try:
        vehicle.run(duration_s=duration_s)
    finally:
        vehicle.close()
        log.info("vehicle stopped: %s", vehicle.counters)
    return 0


def _described(link: Link | SerialLink) -> dict[str, object]:
    """A link in the ready line: its ports, or the serial device the peer opens."""
    if isinstance(link, SerialLink):
        return {"serial": link.path, "baud": link.baud}
    return {"bind": link.bind[1], "remote": link.remote[1]}
