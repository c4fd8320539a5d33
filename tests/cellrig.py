"""Test rig for the cell emulator: the emulator as a real process, a paced sender and a counting sink.

Everything listens on 127.0.0.1; every loop is bounded in time; the emulator is stopped by its pid.
"""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path
from typing import Any

from dynqos.bench.loadgen import Sink, send_paced
from tests.procs import DynqosProcess

__all__ = ["CellProcess", "Sink", "send_paced"]


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
