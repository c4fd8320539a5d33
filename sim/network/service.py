"""`dynqos sim cell`: the emulated cell (sim/network/cell.py) as a process: its control API and the
emulated operator on one port, its Prometheus metrics, stopped by SIGINT/SIGTERM or after a duration."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from dynqos.common.camara import load_private_key, read_headers, read_secret
from dynqos.common.config import BearerConfig, CellConfig, Config
from dynqos.common.errors import ConfigError, DynqosError
from dynqos.common.geo import Geo
from dynqos.common.lifecycle import serving_metrics, stop_loop_on_signals
from dynqos.common.metrics import ProcessMetrics, counter, gauge
from dynqos.sim.network.booking import Bookings
from dynqos.sim.network.cell import CellEmulator
from dynqos.sim.network.control_api import ControlApi, Tap
from dynqos.sim.network.nef import Nef
from dynqos.sim.network.notify import Notifier
from dynqos.sim.network.operator import Operator
from dynqos.sim.network.operator_apis import OperatorApis
from dynqos.sim.network.prediction import Predictor
from dynqos.sim.network.radio import RadioMap
from dynqos.sim.network.radio_feed import RadioFeed
from dynqos.sim.vehicle.world import default_world, load_world

log = logging.getLogger(__name__)


def run(config: Config, *, out_dir: Path | None = None, duration_s: float | None = None) -> int:
    """The cell of `config` ([cell], its bearers from [zenoh] and the drone id; the operator's devices
    and client from [qos.camara]) until stopped; one ready line with the bearer ports."""
    if duration_s is not None and duration_s <= 0:
        raise DynqosError(f"--duration must be > 0, got {duration_s}")
    camara = config.qos.camara
    secret = read_secret(camara.client_secret_file) if config.cell.qod_auth else ""
    # The emulated operator has the client's public key registered: the one of its client_key_file
    client_key = (
        load_private_key(camara.client_key_file).public_key()
        if config.cell.qod_auth and camara.client_key_file
        else None
    )
    api_headers = read_headers(camara.headers_file) if config.cell.qod_auth else {}
    if config.cell.qod_auth and not api_headers and not (camara.client_id and (secret or client_key)):
        raise DynqosError(
            "[cell] qod_auth = true needs [qos.camara] headers_file, or client_id and client_secret_file or "
            "client_key_file"
        )
    devices = {uav: device.as_api() for uav, device in camara.devices.items()}
    with serving_metrics("cell", config) as metrics:
        asyncio.run(
            run_cell(
                config.cell,
                config.cell.bearer_list(config.zenoh, config.drone.id),
                out_dir=out_dir,
                duration_s=duration_s,
                ready=print_ready,
                qod_devices=devices,
                qod_client=(camara.client_id, secret),
                qod_client_key=client_key,
                qod_api_headers=api_headers,
                metrics=metrics,
            )
        )
    return 0


async def run_cell(
    cell: CellConfig,
    bearers: tuple[BearerConfig, ...],
    *,
    out_dir: Path | None = None,
    duration_s: float | None = None,
    ready: Callable[[dict[str, Any]], None] | None = None,
    qod_devices: dict[str, dict[str, Any]] | None = None,
    qod_client: tuple[str, str] = ("", ""),
    qod_client_key: Any = None,
    qod_api_headers: dict[str, str] | None = None,
    tap: Tap | None = None,
    stop: asyncio.Event | None = None,
    metrics: ProcessMetrics | None = None,
) -> dict[str, Any]:
    """Run the emulator until stopped (SIGINT/SIGTERM, `stop` set) or `duration_s`; returns the final
    counters. `qod_devices`: drone id -> CAMARA device, the UEs the operator knows ([cell] qod = true);
    `qod_client`: the (client id, secret) its token endpoint accepts ([cell] qod_auth = true), and
    `qod_client_key` the client's public key for private_key_jwt assertions; `tap`
    sees every control-API exchange (method, path, request JSON, status, response JSON)."""
    if cell.qod and cell.control_port < 0:
        raise ConfigError("cell.control_port", "the QoD API ([cell] qod = true) needs a control port, 0: any")
    emulator, notifier = _build(cell, bearers, out_dir, qod_devices or {}, metrics)
    radio, operator = emulator.radio, emulator.operator
    await emulator.start()
    if metrics is not None:
        metrics.add(lambda: cell_families(emulator))
    control: ControlApi | None = None
    control_port = None
    try:
        await notifier.start()
        if radio is not None:
            await _start_radio(radio, emulator, out_dir)
        if cell.control_port >= 0:
            control = ControlApi(
                emulator,
                operator,
                notifier,
                *qod_client,
                client_key=qod_client_key,
                api_headers=qod_api_headers,
                tap=tap,
            )
            control_port = await _listen(control, cell.control_port)
        stop_loop_on_signals("cell", emulator.loop, emulator.stopped.set)
        info = {
            "ready": True,
            "bearers": {
                b.name: {"port": b.port, "target": f"{b.target[0]}:{b.target[1]}"} for b in emulator.bearers
            },
            "control_port": control_port,
        }
        if radio is not None:
            info["position_port"] = radio.port
        if stop is not None:
            stopper = emulator.loop.create_task(stop.wait())
            stopper.add_done_callback(lambda _: emulator.stopped.set())
        if ready is not None:
            ready(info)
        log.info("cell emulator ready: %s", json.dumps(info))
        if duration_s is not None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(emulator.stopped.wait(), timeout=duration_s)
        else:
            await emulator.stopped.wait()
    finally:
        counters = _final_counters(emulator, out_dir)
        if control is not None:
            await control.stop()
        await notifier.stop()
        if radio is not None:
            radio.close()
        await emulator.stop()
    return counters


def _build(
    cell: CellConfig,
    bearers: tuple[BearerConfig, ...],
    out_dir: Path | None,
    devices: dict[str, dict[str, Any]],
    metrics: ProcessMetrics | None,
) -> tuple[CellEmulator, Notifier]:
    """The cell and its parts, built in the order each needs the other: the radio (from the timeline's
    zero), the operator (its bookings read the radio), the notifier, then the cell around them."""
    start_ns, start_unix = time.monotonic_ns(), time.time()
    radio = _radio(cell, bearers, start_unix)
    operator = _operator(cell, bearers, devices, radio) if cell.qod else None
    notifier = Notifier()
    emulator = CellEmulator(
        cell,
        bearers,
        out_dir,
        operator=operator,
        notify=notifier.send,
        radio=radio,
        start_ns=start_ns,
        beat=metrics.health.beat if metrics is not None else None,
    )
    return emulator, notifier


async def _listen(control: ControlApi, port: int) -> int:
    """The control API on 127.0.0.1:port (0: any free port); the port it took."""
    try:
        return await control.start(port)
    except OSError as exc:
        raise ConfigError(
            "cell.control_port", f"cannot listen on 127.0.0.1:{port} ({exc.strerror})"
        ) from None


def _operator(
    cell: CellConfig,
    bearers: tuple[BearerConfig, ...],
    devices: dict[str, dict[str, Any]],
    radio: RadioFeed | None,
) -> OperatorApis:
    """The emulated operator ([cell] qod = true): its QoD sessions and its bookings."""
    servers = {b.ue: b.target_host_port[0] for b in bearers if b.ue}
    qod = Operator(cell, dict(devices), servers, time.monotonic, time.time)
    nef = Nef(cell, dict(devices), servers, time.monotonic)  # its root: where the control API listens
    return OperatorApis(qod, _bookings(cell, qod, radio), nef if cell.nef else None)


def _bookings(cell: CellConfig, operator: Operator, radio: RadioFeed | None) -> Bookings:
    """The QoS Booking API's bookings: with the radio map on, a booking's area is checked against the
    world's arena and grants only while the cell places the drone inside it."""
    geo = Geo(cell.prediction.origin_lat_deg, cell.prediction.origin_lon_deg)

    def where(uav: str) -> tuple[float, float] | None:
        heard = radio.positions.get(uav) if radio is not None else None
        return (heard[0][0], heard[0][1]) if heard is not None else None

    def covered(x: float, y: float) -> bool:
        return radio is None or radio.predictor.covers(x, y)

    return Bookings(operator, time.time, geo, where, covered, cell.booking_max_concurrent)


def _radio(cell: CellConfig, bearers: tuple[BearerConfig, ...], start_unix: float) -> RadioFeed | None:
    """With [cell.radio] enabled, each drone's rate follows the radio at its position (docs/radio.md);
    `start_unix`: the wall time of the timeline's zero, where the operator's predictions start."""
    config = cell.radio
    if not config.enabled:
        return None
    try:
        world = load_world(config.world_file) if config.world_file else default_world()
    except ConfigError as exc:
        raise ConfigError("cell.radio.world_file", str(exc)) from None
    radio_map = RadioMap(config, world)
    predictor = Predictor(radio_map, cell, world.arena.size_m[:2], start_unix=start_unix)
    return RadioFeed(config, radio_map, bearers, time.monotonic_ns, predictor)


async def _start_radio(feed: RadioFeed, emulator: CellEmulator, out_dir: Path | None) -> None:
    """The vehicles' positions heard, each drone's radio fed into the cell."""
    config = emulator.cell.radio
    try:
        await feed.start(emulator.core, out_dir)
    except OSError as exc:
        where = f"{config.position_host}:{config.position_port}"
        raise ConfigError(
            "cell.radio.position_port", f"cannot listen on {where} for the vehicles' MAVLink ({exc.strerror})"
        ) from None
    log.info(
        "radio map on: %d site(s), %d coverage hole(s); positions heard on udp port %d",
        len(config.sites),
        len(config.holes),
        feed.port,
    )


def _final_counters(emulator: CellEmulator, out_dir: Path | None) -> dict[str, Any]:
    counters = emulator.counters()
    if emulator.operator is not None:
        counters["qod"] = {**vars(emulator.operator.counters), "sessions": emulator.operator.open_sessions()}
        nef = emulator.operator.nef
        if nef is not None:  # its subscriptions, counted apart from the QoD sessions
            counters["qod"]["nef"] = {**vars(nef.counters), "open": len(nef.subscriptions)}
        if out_dir is not None:  # what the operator was left with, once every client has stopped
            (out_dir / "qod.json").write_text(json.dumps(counters["qod"], indent=1) + "\n")
    return counters


def cell_families(emulator: CellEmulator) -> Iterator[Metric]:
    """The cell's per-bearer throughput counters and queue state, for Prometheus (real bytes moved: at
    `--scale F` multiply rates by `dynqos_cell_scale` for the emulated cell's figures)."""
    moved = CounterMetricFamily("dynqos_cell_bytes", "Bytes per bearer and kind", labels=["bearer", "kind"])
    delay = GaugeMetricFamily("dynqos_cell_queue_delay_seconds", "UE buffer delay now", labels=["bearer"])
    buffered = GaugeMetricFamily(
        "dynqos_cell_buffer_bytes", "Bytes waiting in the UE buffer", labels=["bearer"]
    )
    now = time.monotonic_ns()  # the clock the bearers keep
    for bearer in emulator.bearers:
        for kind, value in bearer.totals.items():
            moved.add_metric([bearer.name, kind.removesuffix("_bytes")], value)
        delay.add_metric([bearer.name], bearer.queue_delay_ms(now) / 1000)
        buffered.add_metric([bearer.name], bearer.buffered)
    for user in emulator.background.values():
        moved.add_metric([f"bg:{user.name}", "offered"], user.offered_bits / 8)
        moved.add_metric([f"bg:{user.name}", "delivered"], user.delivered_bits / 8)
    yield moved
    yield delay
    yield buffered
    yield gauge("dynqos_cell_scale", "Every rate of the emulated cell is divided by this", emulator.scale)
    yield gauge(
        "dynqos_cell_capacity_bits_per_second",
        "Uplink capacity now (emulated, unscaled)",
        emulator.current_capacity_mbps(now) * 1e6 * emulator.scale,
    )
    yield counter("dynqos_cell_late_ticks", "Scheduler ticks that ran late", emulator.late_ticks)


def print_ready(info: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(info) + "\n")
    sys.stdout.flush()
