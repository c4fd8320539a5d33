"""A service's health line: to the log every few seconds, to /healthz, and to an optional health file
rewritten atomically each time, so that a Kubernetes exec probe (`dynqos health FILE --max-age S`) can
tell a live service from a hung one: these services listen on no port a TCP probe could check."""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

from dynqos.common.errors import DynqosError

log = logging.getLogger(__name__)


class Health:
    def __init__(
        self,
        name: str,
        interval_s: float = 5.0,
        *,
        file: Path | None = None,
        beat: Callable[[str], None] | None = None,
    ) -> None:
        self.name = name
        self.interval_s = interval_s
        self.file = file
        self.beat = beat  # /healthz's record of the line (common/metrics.py)
        self._next = time.monotonic() + interval_s

    def write(self, line: str) -> None:
        """Replace the health file (if any) with this line and the wall time, atomically."""
        if self.beat is not None:
            self.beat(line)
        if self.file is None:
            return
        record = {"service": self.name, "time_unix": time.time(), "pid": os.getpid(), "health": line}
        tmp = self.file.with_name(self.file.name + ".tmp")
        try:
            tmp.write_text(json.dumps(record) + "\n", encoding="utf-8")
            tmp.replace(self.file)
        except OSError as exc:
            raise DynqosError(f"cannot write health file {self.file}: {exc.strerror}") from None

    def due_in(self) -> float:
        """Seconds until the next line is due (0: now)."""
        return max(0.0, self._next - time.monotonic())

    def maybe(self, line: Callable[[], str]) -> None:
        """Log and write the line if it is due."""
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.interval_s
            text = line()
            log.info("%s health: %s", self.name, text)
            self.write(text)


def check_health(path: Path, max_age_s: float, now_unix: float | None = None) -> str:
    """The health line in `path` if it was written within `max_age_s`; else DynqosError saying why."""
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        age = (time.time() if now_unix is None else now_unix) - float(record["time_unix"])
        line = f"{record['service']}: {record['health']}"
    except OSError as exc:
        raise DynqosError(f"no health file {path} ({exc.strerror}): not started yet or not writing") from None
    except (ValueError, KeyError, TypeError):
        raise DynqosError(f"{path} is not a dynqos health file") from None
    if age > max_age_s:
        raise DynqosError(f"{line}: last health {age:.1f} s ago (max {max_age_s:g} s): hung or stopped")
    return line
