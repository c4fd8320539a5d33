"""Test rig for the cell emulator: the emulator as a real process, a paced sender and a counting sink.

Everything listens on 127.0.0.1; every loop is bounded in time; the emulator is stopped by its pid.
"""

from __future__ import annotations

import json
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dynqos.bench.loadgen import Sink, send_paced
from tests.procs import DynqosProcess

__all__ = ["CellProcess", "Sink", "ZenohThroughCell", "send_paced", "zenoh_through_cell"]


class CellProcess(DynqosProcess):
    """`dynqos sim cell` in its own process, started from a TOML text, stopped by its pid."""

    def __init__(self, tmp_path: Path, toml: str, duration_s: float = 60.0, out: Path | None = None) -> None:
        config = tmp_path / "cell.toml"
        config.write_text(toml)
        args = ["sim", "cell", "--duration", str(duration_s)]
        if out is not None:
            args += ["--out", str(out)]
        super().__init__(args, config)

    def port(self, bearer: str) -> int:
        port: int = self.info["bearers"][bearer]["port"]
        return port

    def counters(self) -> dict[str, Any]:
        url = f"http://127.0.0.1:{self.info['control_port']}/counters"
        with urllib.request.urlopen(url, timeout=5) as response:
            data: dict[str, Any] = json.loads(response.read())
            return data

    def post_event(self, event: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        request = urllib.request.Request(
            f"http://127.0.0.1:{self.info['control_port']}/events",
            data=json.dumps(event).encode(),
            method="POST",
            headers={"Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as response:
                return response.status, json.loads(response.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def __enter__(self) -> CellProcess:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


@dataclass
class ZenohThroughCell:
    """A router, the cell and two zenoh sessions: the edge's on the router, the drone's through the
    cell's two flow bearers (`<uav>-default`, `<uav>-priority`)."""

    cell: CellProcess
    drone: Any  # ZenohBus
    edge: Any


@contextmanager
def zenoh_through_cell(tmp_path: Path, uav: str, cell_keys: str = "") -> Iterator[ZenohThroughCell]:
    """`cell_keys`: more `[cell]` lines (a smaller UE buffer, a scale)."""
    from dynqos.common.config import ZenohConfig
    from dynqos.common.transport import Role, default_flow_endpoint, open_bus, priority_flow_endpoint
    from tests.conftest import flow_ports

    zcfg = ZenohConfig(**flow_ports())
    toml = f"""
[drone]
id = "{uav}"
[zenoh]
default_port = {zcfg.default_port}
priority_port = {zcfg.priority_port}
[cell]
control_port = 0
default_listen_port = 0
priority_listen_port = 0
{cell_keys}
"""
    router = open_bus(zcfg, Role.ROUTER)
    try:
        with CellProcess(tmp_path, toml) as cell:
            edge = open_bus(zcfg, Role.EDGE)
            drone = open_bus(
                zcfg,
                Role.DRONE,
                connect=[
                    default_flow_endpoint(zcfg, port=cell.port(f"{uav}-default")),
                    priority_flow_endpoint(zcfg, port=cell.port(f"{uav}-priority")),
                ],
            )
            try:
                yield ZenohThroughCell(cell, drone, edge)
            finally:
                drone.close()
                edge.close()
    finally:
        router.close()
