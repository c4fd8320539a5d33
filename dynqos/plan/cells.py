"""The config's cell-facing parts once the cell is known: its radio (where it hears the vehicles) and
its ports (where the drone's flows and the QoS agent connect, reported on the cell's ready line)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from dynqos.common.config import Config


def with_radio(config: Config) -> Config:
    """With `[cell.radio] enabled` (docs/radio.md): the cell hears the vehicles' MAVLink on their
    ground-station port and shadows the signal with the vehicles' world."""
    radio = config.cell.radio
    if not radio.enabled:
        return config
    radio = replace(
        radio,
        position_port=config.vehicle.gcs_remote_port,
        world_file=radio.world_file or config.vehicle.world_file,
    )
    return replace(config, cell=replace(config.cell, radio=radio))


def with_cell(config: Config, cell: dict[str, Any], sink_port: int = 0) -> Config:
    """The config once the cell is up: the drone's flows connect to the bearers' ports it reported, and
    the QoS agent asks its control port for QoD sessions and (`sink_port` > 0) takes the operator's
    notifications on that port, as an agent that is told rather than only polling."""
    bearers, uav = cell["bearers"], config.drone.id
    onboard = config.onboard  # a fleet's edge config names no drone of its own
    if f"{uav}-default" in bearers:
        onboard = replace(
            config.onboard,
            connect_default=f"127.0.0.1:{bearers[f'{uav}-default']['port']}",
            connect_priority=f"127.0.0.1:{bearers[f'{uav}-priority']['port']}",
        )
        if config.cell.radio.enabled and onboard.modem == "none":  # the drone's modem is the cell's report
            onboard = replace(
                onboard, modem="cell", modem_url=f"http://127.0.0.1:{cell['control_port']}/radio/{uav}"
            )
    api_root = f"http://127.0.0.1:{cell['control_port']}/quality-on-demand/v1"
    camara = replace(config.qos.camara, api_root=api_root)
    nef = replace(config.qos.nef, api_root=f"http://127.0.0.1:{cell['control_port']}")
    if sink_port:
        sink = f"127.0.0.1:{sink_port}"
        camara = replace(camara, sink=f"http://{sink}/qod-events", sink_listen=sink)
        nef = replace(nef, notification_destination=f"http://{sink}/nef-events", sink_listen=sink)
    qos = replace(config.qos, camara=camara, nef=nef)
    return replace(config, onboard=onboard, qos=qos)
