"""Start `dynqos` subcommands as real processes, wait for their ready line, stop them by pid."""

from __future__ import annotations

import json
import os
import selectors
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

DYNQOS = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")


class DynqosProcess:
    def __init__(
        self,
        args: list[str],
        config: Path,
        ready_timeout_s: float = 30.0,
        env: dict[str, str] | None = None,
        executable: str | Path = DYNQOS,
    ) -> None:
        self.args = args
        self.proc = subprocess.Popen(
            [str(executable), *args, "--config", str(config)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, **env} if env else None,
        )
        assert self.proc.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(self.proc.stdout, selectors.EVENT_READ)
            ready = selector.select(timeout=ready_timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            err = self.stop()
            raise AssertionError(f"dynqos {' '.join(args)} did not become ready: {err[-2000:]}")
        self.info: dict[str, Any] = json.loads(line)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> str:
        """SIGTERM our own child by its pid; kill it if it does not stop. Returns its stderr."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate(timeout=5)
        return err or ""
