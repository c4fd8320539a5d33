"""Where the emulated cell learns each drone's radio: the vehicles' own MAVLink telemetry.

A real network knows where its UEs are from its own measurements, never from the drone's software. The
emulator's stand-in for that is the simulator: every simulated vehicle sends LOCAL_POSITION_NED to its
ground-station port, and the cell listens there as a ground station would (real MAVLink bytes, parsed by
pymavlink), so no onboard or edge code is on the path. Each position goes through the radio map
(sim/network/radio.py); the cell's scheduler gets each bearer's rate factor, `radio.csv` and the control
API's `GET /radio` get what each drone's modem would report.
"""

from __future__ import annotations

import asyncio
import csv
import logging
from pathlib import Path
from typing import Any, TextIO

from pymavlink.dialects.v20 import common as mavlink

from dynqos.common.config import BearerConfig
from dynqos.common.config.radio import RadioConfig
from dynqos.common.message_base import RSRP_RANGE_DBM, SINR_RANGE_DB
from dynqos.sim.network.cell_core import CellCore
from dynqos.sim.network.prediction import Predictor
from dynqos.sim.network.radio import Radio, RadioMap

log = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000


def system_ids(config: RadioConfig, bearers: tuple[BearerConfig, ...]) -> dict[int, str]:
    """MAVLink system id -> drone: as configured, or the cell's drones in order from 1 (PX4 SITL's
    numbering of a fleet: instance N is system id N + 1)."""
    if config.system_ids:
        return {sysid: uav for uav, sysid in config.system_ids.items()}
    ues = list(dict.fromkeys(b.ue for b in bearers if b.ue))
    return {i + 1: uav for i, uav in enumerate(ues)}


class _Listener(asyncio.DatagramProtocol):
    def __init__(self, feed: RadioFeed) -> None:
        self.feed = feed
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        try:
            messages = self.parser.parse_buffer(data) or []
        except mavlink.MAVError:
            self.feed.bad += 1
            return
        for msg in messages:
            if msg.get_msgId() == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                self.feed.heard(msg.get_srcSystem(), (msg.x, msg.y, msg.z))


class RadioFeed:
    """The drones' positions as heard, and their radio from the map."""

    def __init__(
        self,
        config: RadioConfig,
        radio_map: RadioMap,
        bearers: tuple[BearerConfig, ...],
        clock: Any,
        predictor: Predictor,
    ) -> None:
        self.config = config
        self.map = radio_map
        self.predictor = predictor  # what the operator predicts from the same map (GET is the truth)
        self.clock = clock  # () -> ns
        self.uavs = system_ids(config, bearers)
        self.bearers_of: dict[str, list[str]] = {}
        for b in bearers:
            if b.ue:
                self.bearers_of.setdefault(b.ue, []).append(b.name)
        self.positions: dict[str, tuple[tuple[float, float, float], int]] = {}
        self.radio: dict[str, Radio] = {}
        self.bad = 0
        self.unknown: set[int] = set()
        self.port = 0
        self._transport: asyncio.DatagramTransport | None = None
        self._csv_file: TextIO | None = None
        self._csv: Any = None
        self._task: asyncio.Task[None] | None = None

    async def start(self, core: CellCore, out_dir: Path | None) -> int:
        """Listen on the ground-station port and hand `core` the bearers' rate factors every update
        interval; returns the port (the config's, or the one chosen for 0)."""
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Listener(self), local_addr=(self.config.position_host, self.config.position_port)
        )
        self._transport = transport
        self.port = int(transport.get_extra_info("sockname")[1])
        if out_dir is not None:
            self._csv_file = (out_dir / "radio.csv").open("w", newline="")
            self._csv = csv.writer(self._csv_file)
            self._csv.writerow(
                ["t_s", "uav", "x_m", "y_m", "z_m", "rsrp_dbm", "sinr_db", "cqi", "rate_factor"]
            )
        self._task = loop.create_task(self._run(core))
        return self.port

    async def _run(self, core: CellCore) -> None:
        start_ns = core.start_ns
        while True:
            now = self.clock()
            core.rate_factors = self.update(now)
            self.record(f"{(now - start_ns) / NS_PER_S:.3f}")
            await asyncio.sleep(self.config.update_interval_s)

    def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self._transport is not None:
            self._transport.close()
        if self._csv_file is not None:
            self._csv_file.close()

    def heard(self, sysid: int, pos_m: tuple[float, float, float]) -> None:
        uav = self.uavs.get(sysid)
        if uav is None:
            if sysid not in self.unknown:
                self.unknown.add(sysid)
                log.warning("radio: MAVLink system %d is no drone of this cell; its positions ignored", sysid)
            return
        if uav not in self.positions:
            log.info("radio: %s heard at (%.1f, %.1f, %.1f) m", uav, *pos_m)
        self.positions[uav] = (pos_m, self.clock())

    def update(self, now_ns: int) -> dict[str, float]:
        """Each bearer's rate factor now; a drone not heard lately keeps the nominal rate."""
        timeout_ns = round(self.config.position_timeout_s * NS_PER_S)
        factors: dict[str, float] = {}
        for uav, (pos, heard_ns) in list(self.positions.items()):
            if now_ns - heard_ns > timeout_ns:
                log.warning("radio: %s not heard for %.1f s: nominal rate", uav, (now_ns - heard_ns) / 1e9)
                del self.positions[uav]
                self.radio.pop(uav, None)
                continue
            radio = self.map.at(pos)
            previous = self.radio.get(uav)
            if previous is not None and (previous.cqi == 0) != (radio.cqi == 0):
                where = "out of" if radio.cqi == 0 else "back in"
                log.info("radio: %s %s coverage (SINR %.1f dB)", uav, where, radio.sinr_db)
            self.radio[uav] = radio
            factors.update(dict.fromkeys(self.bearers_of.get(uav, ()), radio.rate_factor))
        return factors

    def record(self, t_s: str) -> None:
        if self._csv is None or self._csv_file is None:
            return
        for uav, radio in self.radio.items():
            x, y, z = self.positions[uav][0]
            self._csv.writerow(
                [
                    t_s,
                    uav,
                    f"{x:.2f}",
                    f"{y:.2f}",
                    f"{z:.2f}",
                    f"{radio.rsrp_dbm:.1f}",
                    f"{radio.sinr_db:.1f}",
                    radio.cqi,
                    f"{radio.rate_factor:.3f}",
                ]
            )
        self._csv_file.flush()

    def report(self, uav: str) -> dict[str, Any] | None:
        """What the drone's modem would report now (None: the cell has not placed it)."""
        radio = self.radio.get(uav)
        if radio is None:
            return None
        # a modem reports within 3GPP's ranges: a value below the range is reported as its lowest
        rsrp, sinr = (
            min(max(v, lo), hi)
            for v, (lo, hi) in ((radio.rsrp_dbm, RSRP_RANGE_DBM), (radio.sinr_db, SINR_RANGE_DB))
        )
        return {
            "rsrp_dbm": round(rsrp, 1),
            "sinr_db": round(sinr, 1),
            "cqi": radio.cqi,
            "rate_factor": round(radio.rate_factor, 3),
            "site": radio.site,
            "position_m": [round(c, 2) for c in self.positions[uav][0]],
        }

    def counters(self) -> dict[str, Any]:
        return {
            "port": self.port,
            "drones": {uav: self.report(uav) for uav in self.radio},
            "bad_datagrams": self.bad,
            "unknown_systems": sorted(self.unknown),
        }
