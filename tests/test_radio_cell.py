"""The cell's radio map in the real emulator process: positions arrive as MAVLink LOCAL_POSITION_NED
datagrams (pymavlink's bytes, as a simulated vehicle sends them to its ground station), the modem's view
is served on GET /radio/<uav>, and a drone in a coverage hole gets no uplink until it leaves."""

from __future__ import annotations

import csv
import json
import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink

from tests.cellrig import CellProcess, Sink, send_paced

pytestmark = pytest.mark.timeout(90)


def radio_toml(sink_port: int) -> str:
    return f"""
[cell]
uplink_mbps = 81.3
scale = 10
control_port = 0
jitter_ms = 0

[[cell.bearers]]
name = "drone"
target = "127.0.0.1:{sink_port}"
ue = "uav1"

[cell.radio]
enabled = true
position_port = 0
update_interval_s = 0.05

[[cell.radio.holes]]
center_m = [0.0, -20.0]
radius_m = 3.0
loss_db = 40.0
"""


class Vehicle:
    """Sends LOCAL_POSITION_NED as MAVLink system `sysid` at 20 Hz to the cell until closed (at most 60 s)."""

    def __init__(self, port: int, sysid: int = 1) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.port = port
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self.pos = (0.0, 8.0, -1.5)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        deadline = time.monotonic() + 60
        while not self.stop.wait(0.05) and time.monotonic() < deadline:
            msg = self.mav.local_position_ned_encode(0, *self.pos, 0.0, 0.0, 0.0)
            self.sock.sendto(msg.pack(self.mav), ("127.0.0.1", self.port))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.sock.close()


def get(url: str) -> tuple[int, dict[str, Any]]:
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def wait_radio(url: str, until: Any, within_s: float = 10.0) -> dict[str, Any]:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        status, body = get(url)
        if status == 200 and until(body):
            return body
        threading.Event().wait(0.02)
    raise AssertionError(f"{url}: not as expected within {within_s} s (last: {status} {body})")


def test_a_drone_in_a_coverage_hole_gets_no_uplink_and_its_modem_says_so(tmp_path: Path) -> None:
    sink = Sink()
    out = tmp_path / "run"
    vehicle: Vehicle | None = None
    try:
        with CellProcess(tmp_path, radio_toml(sink.port), out=out) as cell:
            url = f"http://127.0.0.1:{cell.info['control_port']}/radio/uav1"
            status, body = get(url)
            assert status == 404
            assert "no position heard" in body["error"]
            vehicle = Vehicle(cell.info["position_port"])
            stranger = Vehicle(cell.info["position_port"], sysid=9)  # no drone of this cell
            in_air = wait_radio(url, lambda b: b["cqi"] > 0)
            assert in_air["position_m"] == [0.0, 8.0, -1.5]
            assert -90 < in_air["rsrp_dbm"] < -60
            stranger.close()
            sender = threading.Thread(target=send_paced, args=(cell.port("drone"), 1e6, 3.0))
            start = time.monotonic()
            sender.start()
            threading.Event().wait(0.8)
            vehicle.pos = (0.0, -20.0, -1.5)
            in_hole = wait_radio(url, lambda b: b["cqi"] == 0)
            entered = time.monotonic()
            threading.Event().wait(1.0)
            vehicle.pos = (0.0, 8.0, -1.5)
            wait_radio(url, lambda b: b["cqi"] > 0)
            left = time.monotonic()
            sender.join(timeout=30)
            counters = cell.counters()
    finally:
        if vehicle is not None:
            vehicle.close()
        sink.close()
    assert in_hole["rsrp_dbm"] < in_air["rsrp_dbm"] - 35
    assert in_hole["rate_factor"] == 0.0
    assert sink.rate_mbps(start + 0.1, start + 0.7) > 0.5  # 1 Mbit/s offered, carried in the open
    assert sink.rate_mbps(entered + 0.1, left - 0.1) == 0.0  # nothing while in the hole
    assert sink.rate_mbps(left + 0.1, start + 3.0) > 0.5  # the backlog drains once out of it
    assert counters["radio"]["unknown_systems"] == [9]
    with (out / "radio.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert {row["uav"] for row in rows} == {"uav1"}
    assert {int(row["cqi"]) for row in rows} >= {0}
    assert max(int(row["cqi"]) for row in rows) > 0


def test_a_cell_without_a_radio_map_says_so(tmp_path: Path) -> None:
    sink = Sink()
    try:
        toml = radio_toml(sink.port).replace("enabled = true", "enabled = false")
        with CellProcess(tmp_path, toml) as cell:
            status, body = get(f"http://127.0.0.1:{cell.info['control_port']}/radio/uav1")
            assert "position_port" not in cell.info
            assert "radio" not in cell.counters()
    finally:
        sink.close()
    assert status == 404
    assert "no radio map" in body["error"]
