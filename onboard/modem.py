"""What the drone's 5G modem says about its radio: RSRP and SINR, read once a second off the tick thread.

The paper asks for a proactive input besides measured latency: a modem sees its signal fade before
the queue grows. Two sources read it. `mmcli`: ModemManager's command line on a real drone
(`mmcli -m any --signal-get --output-json`: `modem.signal.5g.rsrp` and `.snr` as strings, "--" when
unknown; extended signal readings need `--signal-setup=<seconds>` once, which the poller runs). `cell`:
the emulated cell's `GET /radio/<uav>`, which reports what a modem would at the position where the cell
last heard the vehicle (docs/radio.md). Either way a reading outside what a modem can report is dropped.
"""

from __future__ import annotations

import json
import logging
import shlex
import subprocess
import threading
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dynqos.common.message_base import RSRP_RANGE_DBM, SINR_RANGE_DB

log = logging.getLogger(__name__)

MMCLI_TIMEOUT_S = 5.0
Read = Callable[[], tuple[float | None, float | None]]


class ModemError(Exception):
    """A reading that could not be taken or understood; the message says why."""


@dataclass(frozen=True, slots=True)
class ModemReading:
    rsrp_dbm: float | None
    sinr_db: float | None
    stamp_ns: int


def _within(value: Any, bounds: tuple[float, float]) -> float | None:
    """A number within a modem's reporting range, or None (unknown, "--", or out of range)."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if bounds[0] <= number <= bounds[1] else None


def parse_mmcli(text: str) -> tuple[float | None, float | None]:
    """(RSRP, SINR) from `mmcli --signal-get --output-json`: 5G NR's, or LTE's when the modem has no NR."""
    try:
        signal = json.loads(text)["modem"]["signal"]
    except (ValueError, KeyError, TypeError):
        raise ModemError("mmcli printed no modem.signal JSON") from None
    if not isinstance(signal, dict):
        raise ModemError("mmcli's modem.signal is not an object")
    for tech in ("5g", "lte"):
        values = signal.get(tech)
        if isinstance(values, dict):
            rsrp = _within(values.get("rsrp"), RSRP_RANGE_DBM)
            sinr = _within(values.get("snr"), SINR_RANGE_DB)
            if rsrp is not None or sinr is not None:
                return rsrp, sinr
    return None, None


def parse_cell(body: Any) -> tuple[float | None, float | None]:
    """(RSRP, SINR) from the emulated cell's GET /radio/<uav>."""
    if not isinstance(body, dict):
        raise ModemError("the cell's radio report is not a JSON object")
    return _within(body.get("rsrp_dbm"), RSRP_RANGE_DBM), _within(body.get("sinr_db"), SINR_RANGE_DB)


def read_mmcli(command: str) -> tuple[float | None, float | None]:
    try:
        done = subprocess.run(
            shlex.split(command), capture_output=True, text=True, timeout=MMCLI_TIMEOUT_S, check=False
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise ModemError(f"cannot run {command!r}: {exc}") from None
    if done.returncode != 0:
        raise ModemError(f"{command!r} exited {done.returncode}: {done.stderr.strip()[:200]}")
    return parse_mmcli(done.stdout)


def read_cell(url: str) -> tuple[float | None, float | None]:
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return parse_cell(json.loads(response.read()))
    except urllib.error.HTTPError as exc:
        if exc.code == 404:  # the cell has not placed the drone (yet): no reading, no error
            return None, None
        raise ModemError(f"{url}: HTTP {exc.code}") from None
    except (OSError, ValueError) as exc:
        raise ModemError(f"{url}: {exc}") from None


class ModemPoller:
    """Reads the modem every `interval_s` on its own thread; `latest` is the newest reading (or None)."""

    def __init__(
        self,
        read: Read,
        interval_s: float,
        clock: Callable[[], int],
        stop: threading.Event,
        name: str,
        setup: Callable[[], None] | None = None,
    ) -> None:
        self.read = read
        self.setup = setup  # run once on the poller's thread before the first reading
        self.interval_s = interval_s
        self.clock = clock
        self.stop = stop
        self.name = name
        self.latest: ModemReading | None = None
        self.failures = 0
        self.thread = threading.Thread(target=self._run, name="modem", daemon=True)

    def start(self) -> None:
        self.thread.start()

    def _run(self) -> None:
        if self.setup is not None:
            self.setup()
        failing = False
        while not self.stop.is_set():
            try:
                rsrp, sinr = self.read()
            except ModemError as exc:
                self.failures += 1
                if not failing:
                    log.warning(
                        "modem (%s): no reading: %s; retrying every %.1f s", self.name, exc, self.interval_s
                    )
                failing = True
            else:
                if failing:
                    log.info("modem (%s): readings again", self.name)
                failing = False
                self.latest = ModemReading(rsrp, sinr, self.clock())
            self.stop.wait(self.interval_s)


def modem_poller(
    source: str, url: str, command: str, interval_s: float, clock: Callable[[], int], stop: threading.Event
) -> ModemPoller | None:
    """The poller of `[onboard] modem` (None for "none")."""
    if source == "cell":
        return ModemPoller(lambda: read_cell(url), interval_s, clock, stop, f"cell {url}")
    if source == "mmcli":
        return ModemPoller(
            lambda: read_mmcli(command),
            interval_s,
            clock,
            stop,
            "mmcli",
            setup=lambda: mmcli_setup(command, interval_s),
        )
    return None


def mmcli_setup(command: str, interval_s: float) -> None:
    """ModemManager keeps extended signal readings off until asked for a refresh rate; a modem that
    refuses still answers --signal-get (with less), so a failure is logged, not fatal."""
    args = shlex.split(command.replace("--signal-get", f"--signal-setup={max(1, round(interval_s))}"))
    args = [a for a in args if a not in ("--output-json", "-J")]
    try:
        done = subprocess.run(args, capture_output=True, text=True, timeout=MMCLI_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        log.warning("modem (mmcli): %s failed: %s", shlex.join(args), exc)
        return
    if done.returncode != 0:
        log.warning(
            "modem (mmcli): %s exited %d: %s", shlex.join(args), done.returncode, done.stderr.strip()[:200]
        )
