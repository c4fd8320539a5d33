"""`dynqos view` and `dynqos record`: subscribe to the dynqos keys as an edge client and feed them,
through `telemetry`, to the Foxglove app over its WebSocket protocol and/or to an MCAP file, with the
official foxglove-sdk (its server and its MCAP sink: one channel layer for both).

An observer must not slow the loop it watches (docs/observability.md, the `observability` benchmark):
zenoh's callback only copies the payload into one bounded queue (the newest kept when it overflows,
the drops counted); one worker wakes every BATCH_S, decodes, converts and logs what arrived, in arrival
order, so each channel's log times only grow; and the process runs niced below the control path.
Time base: wall-clock nanoseconds taken once at start and advanced by the monotonic clock, so a clock
step cannot make a recording go backwards.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import foxglove
import zenoh

from dynqos import __version__
from dynqos.common import keys
from dynqos.common.config import Config, to_toml
from dynqos.common.errors import DecodeError, DynqosError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.lifecycle import ready_line, stop_on_signals
from dynqos.common.messages import CameraFrame, decode
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Role, ZenohBus, open_bus
from dynqos.edge.detector.assembler import FrameAssembler
from dynqos.observers.telemetry import Out, Telemetry, frames, json_schema_for, world_scene
from dynqos.sim.vehicle.world import World, default_world, load_world

log = logging.getLogger(__name__)

QUEUE_MESSAGES = 4096
BATCH_S = 0.05  # the worker's wake-up period: a display's 20 Hz, away from each state's arrival
OBSERVER_NICE = 10
LINGER_S = 0.5  # on stop: quiet this long means nothing is in flight any more
LINGER_MAX_S = 3.0
STATIC_EVERY_S = 2.0  # /tf and /world again, for a viewer that connects late


def subscriptions(uav: str | None, camera: bool) -> list[str]:
    """The keys to watch: every drone's, or one drone's."""
    ups = [Stream.STATE, Stream.STATUS] + ([Stream.CAMERA_RGB] if camera else [])
    downs = [Downlink.REFERENCE, Downlink.DETECTIONS, Downlink.QOS_GRANT, Downlink.QOS_DECISION]
    if uav is None:
        return [keys.uplink_all_drones(s) for s in ups] + [keys.downlink_all_drones(d) for d in downs]
    return [keys.uplink_any_flow(uav, s) for s in ups] + [keys.downlink(uav, d) for d in downs]


@dataclass
class Counts:
    received: int = 0
    rejected: int = 0
    logged: dict[str, int] = field(default_factory=dict)  # per topic


class Observer:
    """The zenoh side and the channel layer; sinks (server, MCAP) are attached to `context`."""

    def __init__(self, config: Config, world: World, *, uav: str | None = None, camera: bool = True) -> None:
        self.config = config
        self.world = world
        self.context = foxglove.Context()
        self.telemetry = Telemetry()
        self.assembler = FrameAssembler()
        self.queue: BoundedQueue[tuple[str, bytes]] = BoundedQueue(QUEUE_MESSAGES)
        self.channels: dict[str, Any] = {}
        self.counts = Counts()
        self.stop = threading.Event()
        self.keys = subscriptions(uav, camera)
        self.bus: ZenohBus | None = None
        self.subscribers: list[Any] = []  # held for the session's lifetime
        self._wall0 = time.time_ns()
        self._mono0 = time.monotonic_ns()

    def now_ns(self) -> int:
        return self._wall0 + time.monotonic_ns() - self._mono0

    def open(self) -> None:
        self.bus = open_bus(self.config.zenoh, Role.EDGE)
        self.subscribers = [self.bus.session.declare_subscriber(key, self._on_sample) for key in self.keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.queue.put((str(sample.key_expr), sample.payload.to_bytes()))

    def run(self) -> None:
        """Convert and log until `stop`; then what is already queued, so a clean stop loses nothing."""
        next_static = 0.0
        while not self.stop.wait(BATCH_S):
            if time.monotonic() >= next_static:
                next_static = time.monotonic() + STATIC_EVERY_S
                self.log_all([frames(self.now_ns()), world_scene(self.world, self.now_ns())])
            for key, payload in self.queue.drain():
                self.take(key, payload)
        self._flush()

    def _flush(self) -> None:
        """On stop, what is still in flight: take samples until none has come for LINGER_S (at most
        LINGER_MAX_S), so that a recording stopped right after the drone keeps its last messages."""
        deadline = time.monotonic() + LINGER_MAX_S
        while time.monotonic() < deadline:
            item = self.queue.get(LINGER_S)
            if item is None:
                return
            self.take(*item)

    def take(self, key: str, payload: bytes) -> None:
        try:
            message = decode(payload)
        except DecodeError as exc:
            self.counts.rejected += 1
            if self.counts.rejected == 1:
                log.warning("%s: undecodable message on %s: %s", "observer", key, exc)
            return
        self.counts.received += 1
        if isinstance(message, CameraFrame):
            whole = self.assembler.add(message)
            if whole is None:
                return
            message = whole
        self.log_all(self.telemetry.convert(message, self.now_ns()))

    def log_all(self, outs: list[Out]) -> None:
        now = self.now_ns()
        for topic, payload in outs:
            self._channel(topic, payload).log(payload, log_time=now)
            self.counts.logged[topic] = self.counts.logged.get(topic, 0) + 1

    def _channel(self, topic: str, payload: Any) -> Any:
        channel = self.channels.get(topic)
        if channel is None:
            if isinstance(payload, dict):
                channel = foxglove.Channel(
                    topic, schema=json_schema_for(topic), message_encoding="json", context=self.context
                )
            else:
                typed = getattr(foxglove.channels, type(payload).__name__ + "Channel")
                channel = typed(topic, context=self.context)
            self.channels[topic] = channel
        return channel

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
            self.bus = None

    def summary(self) -> str:
        topics = " ".join(f"{t}={n}" for t, n in sorted(self.counts.logged.items()))
        c = self.counts
        return f"received={c.received} rejected={c.rejected} dropped={self.queue.dropped} {topics}"


def open_recording(observer: Observer, path: Path, scenario: str = "") -> Any:
    """An MCAP sink on the observer's channels, with the metadata that makes the file self-describing."""
    if path.suffix != ".mcap":
        raise DynqosError(f"--out {path}: an MCAP file name ends in .mcap")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=observer.context)
    except OSError as exc:
        raise DynqosError(f"cannot write {path}: {exc.strerror or exc}") from None
    writer.write_metadata(
        "dynqos",
        {
            "version": __version__,
            "scenario": scenario,
            "keys": " ".join(observer.keys),
            "started_unix_ns": str(observer.now_ns()),
        },
    )
    writer.write_metadata("dynqos.config", {"toml": to_toml(observer.config)})
    return writer


def start_viewer(observer: Observer, host: str, port: int) -> Any:
    try:
        return foxglove.start_server(name="dynqos", host=host, port=port, context=observer.context)
    except RuntimeError as exc:  # the SDK's "FoxgloveError: Failed to bind port: ..."
        raise DynqosError(f"cannot serve the Foxglove WebSocket on {host}:{port}: {exc}") from None


def run(
    config: Config,
    *,
    view: bool,
    record: Path | None = None,
    uav: str | None = None,
    world_file: str | None = None,
    camera: bool = True,
    host: str = "127.0.0.1",
    port: int = 8765,
    scenario: str = "",
) -> int:
    """`dynqos view` (`view`: a Foxglove WebSocket server) and/or `dynqos record` (`record`: an MCAP
    file) until SIGTERM or Ctrl-C; niced below the control path, and the MCAP closed whole."""
    name = "view" if view else "record"
    os.nice(OBSERVER_NICE)  # below the control path on a shared machine: watching must not slow the loop
    world = load_world(world_file) if world_file else default_world()
    observer = Observer(config, world, uav=uav, camera=camera)
    writer = open_recording(observer, record, scenario=scenario) if record else None
    server = start_viewer(observer, host, port) if view else None
    stop_on_signals(name, observer.stop.set)
    try:
        observer.open()
        info: dict[str, Any] = {"keys": observer.keys}
        if server is not None:
            info["port"] = server.port
            log.info("view: Foxglove WebSocket on ws://%s:%d (open it in Foxglove)", host, server.port)
        if record is not None:
            info["out"] = str(record)
        ready_line(name, **info)
        observer.run()
    finally:
        observer.close()
        if writer is not None:
            writer.close()  # the MCAP's summary and footer: a complete file
        if server is not None:
            server.stop()
        log.info("%s: stopped; %s", name, observer.summary())
    return 0
