"""The cell emulator with real bytes on 127.0.0.1: Table II physics, records, control API, zenoh."""

from __future__ import annotations

import contextlib
import csv
import threading
import time
from pathlib import Path

import pytest

from tests.cellrig import CellProcess, Sink, send_paced, zenoh_through_cell

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def cell_toml(sink_port: int, *, weight: float, scale: float, bg_mbps: float = 80.0, extra: str = "") -> str:
    return f"""
[cell]
uplink_mbps = 81.3
scale = {scale}
ue_buffer_bytes = {max(1500, round(4_000_000 / scale))}
control_port = 0
base_delay_up_ms = 10
base_delay_down_ms = 10
jitter_ms = 0

[[cell.bearers]]
name = "drone"
target = "127.0.0.1:{sink_port}"
weight = {weight}

[[cell.background]]
name = "bg"
offered_mbps = {bg_mbps}
{extra}
"""


def run_table_ii(tmp_path: Path, weight: float, scale: float) -> tuple[float, list[float], float]:
    """Offer 47 Mbit/s (/scale) for 4 s against 80 Mbit/s background; returns the drone's delivered
    Mbit/s over 1-4 s, its queue delay at 1.5, 2.5 and 3.5 s, and the background's delivered Mbit/s
    over 1-3.5 s (rates scaled back to the unscaled cell)."""
    sink = Sink()
    chunk = max(1024, round(16 * 1024 / scale))  # the sender's bursts shrink with its rate
    try:
        with CellProcess(tmp_path, cell_toml(sink.port, weight=weight, scale=scale)) as cell:
            port = cell.port("drone")
            start = time.monotonic()
            sender = threading.Thread(target=send_paced, args=(port, 47e6 / scale, 4.0, chunk))
            sender.start()
            delays = []
            samples = []
            for at in (1.0, 1.5, 2.5, 3.5):
                threading.Event().wait(max(0.0, start + at - time.monotonic()))  # sample at fixed instants
                counters = cell.counters()
                samples.append((counters["t_s"], counters["background"]["bg"]["delivered_bits"]))
                if at > 1.0:
                    delays.append(counters["bearers"]["drone"]["queue_delay_ms"])
            sender.join(timeout=30)
            delivered = sink.rate_mbps(start + 1.0, start + 4.0) * scale
            (t0, bits0), (t1, bits1) = samples[0], samples[-1]
            bg = (bits1 - bits0) / (t1 - t0) / 1e6 * scale
    finally:
        sink.close()
    return delivered, delays, bg


@pytest.mark.parametrize("scale", [10.0, pytest.param(1.0, marks=pytest.mark.slow)])
def test_equal_weights_split_the_cell_and_the_drone_queue_grows(tmp_path: Path, scale: float) -> None:
    delivered, delays, bg = run_table_ii(tmp_path, weight=1.0, scale=scale)
    print(f"scale {scale}: drone {delivered:.2f} Mbit/s, bg {bg:.2f} Mbit/s, queue delay {delays} ms")
    assert delivered == pytest.approx(40.65, rel=0.10)
    assert bg == pytest.approx(40.65, rel=0.10)
    assert delays[2] > delays[1] > delays[0], "the drone's queue delay should grow"
    assert delays[2] > delays[0] + 100


@pytest.mark.parametrize("scale", [10.0, pytest.param(1.0, marks=pytest.mark.slow)])
def test_priority_weight_keeps_the_drone_rate_and_a_flat_queue(tmp_path: Path, scale: float) -> None:
    delivered, delays, bg = run_table_ii(tmp_path, weight=4.0, scale=scale)
    print(f"scale {scale}: drone {delivered:.2f} Mbit/s, bg {bg:.2f} Mbit/s, queue delay {delays} ms")
    assert delivered >= 45.0
    assert max(delays) < 10.0
    assert bg == pytest.approx(81.3 - 47.0, rel=0.10)


def test_records_and_control_api(tmp_path: Path) -> None:
    sink = Sink()
    out = tmp_path / "run"
    try:
        with CellProcess(
            tmp_path, cell_toml(sink.port, weight=1.0, scale=10.0, bg_mbps=0.0), out=out
        ) as cell:
            status, body = cell.post_event({"kind": "background", "user": "bg", "offered_mbps": 50})
            assert status == 200, body
            assert "50" in body["applied"]
            status, body = cell.post_event({"kind": "background", "user": "nobody", "offered_mbps": 5})
            assert status == 400
            assert "unknown background user" in body["error"]
            status, body = cell.post_event({"kind": "capacity", "uplink_mbps": -3})
            assert status == 400
            assert "uplink_mbps" in body["error"]
            send_paced(cell.port("drone"), 1e6, 0.5)
            counters = cell.counters()
            assert counters["background"]["bg"]["offered_mbps_now"] == pytest.approx(50.0)
            assert counters["bearers"]["drone"]["offered_bytes"] > 0
    finally:
        sink.close()
    with (out / "cell.csv").open() as f:
        rows = list(csv.DictReader(f))
    names = {row["name"] for row in rows}
    assert names == {"drone", "bg"}
    assert sum(int(row["offered_bits"]) for row in rows if row["name"] == "drone") > 0
    assert float(rows[-1]["t_s"]) > 0.4


def test_coverage_loss_stops_delivery_and_resumes(tmp_path: Path) -> None:
    sink = Sink()
    try:
        with CellProcess(tmp_path, cell_toml(sink.port, weight=1.0, scale=10.0, bg_mbps=0.0)) as cell:
            port = cell.port("drone")
            sender = threading.Thread(target=send_paced, args=(port, 2e6, 3.0))
            start = time.monotonic()
            sender.start()
            threading.Event().wait(0.5)
            assert cell.post_event({"kind": "coverage_loss", "duration_s": 1.0})[0] == 200
            lost_at = time.monotonic()
            sender.join(timeout=30)
            during = sink.rate_mbps(lost_at + 0.1, lost_at + 0.9)
            after = sink.rate_mbps(lost_at + 1.1, start + 3.0)
    finally:
        sink.close()
    assert during == 0.0
    assert after > 1.0  # the backlog drains after coverage returns


def test_downlink_loss_holds_the_downlink_and_keeps_the_uplink(tmp_path: Path) -> None:
    """One byte each 50 ms through the cell to an echo server: during a 1 s downlink loss the echo
    server keeps receiving (uplink), while the drone gets its echoes only after the loss."""
    import socket

    server = socket.create_server(("127.0.0.1", 0))
    received_at: list[float] = []

    def echo() -> None:
        conn, _ = server.accept()
        with conn:
            while data := conn.recv(4096):
                received_at.append(time.monotonic())
                conn.sendall(data)

    thread = threading.Thread(target=echo, daemon=True)
    thread.start()
    echoed_at: list[float] = []
    try:
        toml = cell_toml(server.getsockname()[1], weight=1.0, scale=1.0, bg_mbps=0.0)
        with CellProcess(tmp_path, toml) as cell:
            drone = socket.create_connection(("127.0.0.1", cell.port("drone")), timeout=10)
            with drone:
                drone.settimeout(0.01)
                start = time.monotonic()
                lost_at = None
                while (now := time.monotonic()) - start < 3.0:  # bounded: 3 s, 60 bytes
                    if lost_at is None and now - start >= 0.5:
                        assert cell.post_event({"kind": "downlink_loss", "duration_s": 1.0})[0] == 200
                        lost_at = time.monotonic()
                    drone.sendall(b"x")
                    with contextlib.suppress(TimeoutError):
                        echoed_at += [time.monotonic()] * len(drone.recv(4096))
                    time.sleep(0.04)  # pacing the probe bytes, not synchronisation
    finally:
        server.close()
        thread.join(timeout=5)
    assert lost_at is not None
    uplink_during = [t for t in received_at if lost_at + 0.1 < t < lost_at + 0.9]
    downlink_during = [t for t in echoed_at if lost_at + 0.1 < t < lost_at + 0.9]
    assert len(uplink_during) >= 10  # the uplink went on
    assert downlink_during == []  # nothing came down
    assert len(echoed_at) >= len(received_at) - 3  # and everything held came down afterwards


def test_zenoh_flow_links_pass_through_their_two_bearers(tmp_path: Path) -> None:
    from dynqos.common import keys
    from dynqos.common.keys import Flow, Stream
    from dynqos.common.messages import State
    from dynqos.common.queues import BoundedQueue
    from dynqos.common.transport import Priority, Received

    with zenoh_through_cell(tmp_path, "uav7") as rig:
        cell, drone, edge = rig.cell, rig.drone, rig.edge
        assert sorted(link.priorities or (0, 0) for link in drone.links()) == [(1, 3), (4, 7)]
        queue: BoundedQueue[Received] = BoundedQueue(100)
        edge.subscribe(keys.uplink_any_flow("uav7", Stream.STATE), queue)
        publisher = drone.publisher(keys.uplink("uav7", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
        assert publisher.wait_matched(10)
        before = cell.counters()["bearers"]
        sent = time.monotonic_ns()
        for seq in range(20):
            state = State(uav="uav7", seq=seq, stamp_ns=sent, pos_m=(0, 0, -1), vel_mps=(0, 0, 0),
                          quat=(1, 0, 0, 0))  # fmt: skip
            publisher.put(state)
        got = [queue.get(timeout_s=10) for _ in range(20)]
        assert all(item is not None for item in got)
        one_way_ms = (got[0].arrival_ns - sent) / 1e6  # type: ignore[union-attr]
        after = cell.counters()["bearers"]
    assert after["uav7-priority"]["offered_bytes"] - before["uav7-priority"]["offered_bytes"] > 20 * 50
    assert after["uav7-default"]["offered_bytes"] - before["uav7-default"]["offered_bytes"] < 20 * 50
    assert after["uav7-priority"]["weight"] == 4.0
    assert one_way_ms >= 10.0  # the emulated uplink delay is on the path


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ("[cell]\nuplink_mbps = -5\n", "cell.uplink_mbps: must be in 0..100000"),
        ("[cell]\nscale = 0\n", "cell.scale"),
        (
            '[[cell.events]]\nat_s = 1\nkind = "weight"\nbearer = "nope"\nweight = 2\n',
            "unknown bearer 'nope'",
        ),
        (
            '[[cell.events]]\nat_s = 1\nkind = "background"\nuser = "x"\noffered_mbps = 2\n',
            "unknown background",
        ),
        ('[[cell.events]]\nat_s = 1\nkind = "teleport"\n', "cell.events[0].kind"),
        ('[cell]\ntrace = "/nonexistent/trace.up"\n', "cell.trace: /nonexistent/trace.up: cannot read trace"),
        ('[[cell.bearers]]\nname = "a"\ntarget = "nohost"\n', "cell.bearers[0].target"),
    ],
)
def test_bad_cell_config_is_one_line_and_exit_2(tmp_path: Path, toml: str, message: str) -> None:
    import subprocess

    from tests.procs import DYNQOS

    path = tmp_path / "bad.toml"
    path.write_text(toml)
    result = subprocess.run(
        [DYNQOS, "sim", "cell", "--config", str(path), "--duration", "1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert message in lines[0]


def test_trace_driven_capacity_limits_delivery(tmp_path: Path) -> None:
    trace = tmp_path / "flat.up"
    trace.write_text("".join(f"{ms}\n" for ms in range(1, 1001)))  # one 1500-byte packet per ms: 12 Mbit/s
    sink = Sink()
    try:
        toml = cell_toml(sink.port, weight=1.0, scale=1.0, bg_mbps=0.0).replace(
            "[cell]\n", f'[cell]\ntrace = "{trace}"\n', 1
        )
        with CellProcess(tmp_path, toml) as cell:
            start = time.monotonic()
            send_paced(cell.port("drone"), 20e6, 3.0)
            delivered = sink.rate_mbps(start + 1.0, start + 3.0)
            assert cell.counters()["capacity_mbps"] == pytest.approx(12.0, rel=0.01)
    finally:
        sink.close()
    assert delivered == pytest.approx(12.0, rel=0.1)
