"""`dynqos onboard check`: the preflight a person runs on the drone before a flight, with the drone's own
config. One line per item, PASS or FAIL and what was found; exit 0 only if every item passes.

Items: the flight controller (heartbeat, mode, armed, the position and attitude rates it gives after
being asked for 50 Hz), MAVLink signing (on and every message checked, or off, said as a risk), the
camera (frames, size, the fraction of valid depth), the edge router on each flow (a zenoh session
opened as this drone, with its certificate where TLS is on), the wall-clock offset to the edge
(onboard/clock_offset.py), the QoS settings, each offloaded task's module, and the systemd unit.
Nothing is armed, no setpoint is sent, nothing is published to any other process (the clock probes go
to the router and back).
"""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dynqos.common.config import Config
from dynqos.common.errors import DynqosError
from dynqos.common.keys import clock_probe
from dynqos.common.transport import Role, ZenohBus, open_bus
from dynqos.onboard import clock_offset
from dynqos.onboard.fclink import FcLink

MIN_POSITION_HZ = 40.0  # the control loop needs a fresh state (position, attitude) every 20 ms tick
UNIT = "dynqos-onboard.service"


@dataclass(frozen=True, slots=True)
class Item:
    name: str
    ok: bool
    detail: str

    def line(self) -> str:
        return f"{'PASS' if self.ok else 'FAIL'}  {self.name:<22} {self.detail}"


def check_fc(config: Config, measure_s: float) -> list[Item]:
    """The FC and its link's signing: heard within fc_timeout_s, then its position rate over measure_s."""
    from dynqos.onboard.parts import fc_link

    cfg = config.onboard
    link = fc_link(config)
    signing = bool(cfg.mavlink_signing_key)
    try:
        link.start()
        if not link.wait_ready(cfg.fc_timeout_s):
            fc = Item(
                "flight controller", False, f"nothing heard on {cfg.mavlink_url} in {cfg.fc_timeout_s:g} s"
            )
            return [fc, _signing(link, signing)]
        before = link.positions, link.attitudes
        time.sleep(measure_s)  # a rate is counted over time
        rate = (link.positions - before[0]) / measure_s
        attitude = (link.attitudes - before[1]) / measure_s
        main, sub = (link.custom_mode >> 16) & 0xFF, (link.custom_mode >> 24) & 0xFF
        detail = (
            f"system {cfg.fc_system_id}, mode {main}/{sub}, {'armed' if link.armed else 'disarmed'}, "
            f"position {rate:.0f} Hz, attitude {attitude:.0f} Hz (need {MIN_POSITION_HZ:g} each)"
        )
        ok = min(rate, attitude) >= MIN_POSITION_HZ
        return [Item("flight controller", ok, detail), _signing(link, signing)]
    finally:
        link.close()


def _signing(link: FcLink, on: bool) -> Item:
    if not on:
        return Item("MAVLink signing", True, "off: anyone on the link can command the FC (docs/onboard.md)")
    counts = link.signing_counts()
    checked, refused = counts["signed_ok"], counts["refused"]
    if checked == 0 and refused == 0:
        return Item("MAVLink signing", True, "on: nothing heard to check (see the flight controller)")
    return Item("MAVLink signing", refused == 0, f"on: {checked} signed messages checked, {refused} refused")


def check_camera(config: Config, measure_s: float) -> Item:
    """Frames from the configured source over measure_s: count, size, valid depth."""
    from dynqos.onboard.parts import camera_source

    cfg = config.onboard
    if cfg.camera == "none" or cfg.camera_fps == 0:
        return Item("camera", True, "none configured: no risk input (read as MR)")
    if cfg.camera == "sim":
        return Item("camera", True, "sim: rendered by the simulator, nothing to check on the drone")
    try:
        source = camera_source(config, None)
    except DynqosError as exc:
        return Item("camera", False, str(exc))
    assert source is not None
    frames, valid, size = 0, [], ""
    asked = max(1, round(measure_s * cfg.camera_fps))
    start = time.monotonic()
    for k in range(asked):  # at the daemon's camera rate: does the source keep up with it?
        time.sleep(max(0.0, start + k / cfg.camera_fps - time.monotonic()))
        raw = source.grab(None)
        if raw is None:
            continue
        frames += 1
        size = f"{raw.rgb.shape[1]}x{raw.rgb.shape[0]}"
        if raw.depth_m is not None:
            valid.append(float(np.count_nonzero(raw.depth_m > 0)) / raw.depth_m.size)
    close = getattr(source, "close", None)
    if close is not None:
        close()
    got = f"{frames} of {asked} frames at {cfg.camera_fps:g} fps"
    if frames < 0.8 * asked:
        return Item("camera", False, f"{cfg.camera}: only {got}")
    depth = (
        f"valid depth {100 * min(valid):.0f}-{100 * max(valid):.0f}%" if valid else "no depth (no risk input)"
    )
    return Item("camera", bool(valid), f"{cfg.camera}: {got}, {size}, {depth}")


def check_router(config: Config) -> list[Item]:
    """A session opened as this drone to each flow's endpoint of each path (its certificate where TLS is
    on), and the clock offset to the router of the first path's default flow."""
    from dynqos.onboard.links import path_endpoints

    items = []
    clock = Item("clock offset to edge", False, "no router reached on the default flow to ask")
    asked = False
    for path, endpoints in path_endpoints(config).items():
        router = f"router {path}" if path else "router"
        for name, endpoint in zip(
            (f"{router}, default flow", f"{router}, priority flow"), endpoints, strict=True
        ):
            try:
                bus = open_bus(config.zenoh, Role.DRONE, connect=[endpoint])
            except DynqosError as exc:
                why = str(exc).rsplit("): ", 1)[-1]
                if why.startswith("Unable to connect"):
                    why = "nothing accepts a connection there"
                items.append(Item(name, False, f"{endpoint.split('?')[0]}: {why[:120]}"))
                asked = True
                continue
            try:
                if not asked:  # the first path's default flow
                    clock = check_clock(config, bus, endpoint)
            finally:
                bus.close()
            asked = True
            items.append(Item(name, True, f"{endpoint.split('?')[0]} reached as {config.drone.id}"))
    return [*items, clock]


def _router_ns(sample: Any) -> int | None:
    stamp = sample.timestamp
    if stamp is None:
        return None
    seconds: float = stamp.get_time().timestamp()  # a datetime, to the microsecond
    return round(seconds * 1e6) * 1000


def probe_clock(
    sender: Any, receiver: Any, key: str, timeout_s: float
) -> tuple[list[clock_offset.Probe], int]:
    """PROBES probes put by `sender` and received by `receiver` (two zenoh sessions), a probe every
    PROBE_EVERY_S until all came or timeout_s passed (onboard/clock_offset.py); also how many arrived
    without a router stamp."""
    lock = threading.Lock()
    sent: dict[int, int] = {}
    probes: list[clock_offset.Probe] = []
    unstamped = [0]
    done = threading.Event()

    def on_sample(sample: Any) -> None:
        received = time.time_ns()
        router = _router_ns(sample)
        with lock:
            index = int(sample.payload.to_bytes() or b"-1")
            if index not in sent:
                return
            if router is None:
                unstamped[0] += 1
            else:
                probes.append(clock_offset.Probe(sent.pop(index), router, received))
            if len(probes) >= clock_offset.PROBES:
                done.set()

    subscriber = receiver.declare_subscriber(key, on_sample)
    try:
        deadline = time.monotonic() + timeout_s
        index = 0
        # a retry loop, not a wait for the subscription to travel: probes before it arrived are lost
        while not done.is_set() and time.monotonic() < deadline:
            with lock:
                sent[index] = time.time_ns()
            sender.put(key, str(index).encode())
            index += 1
            done.wait(clock_offset.PROBE_EVERY_S)
    finally:
        subscriber.undeclare()
    with lock:
        return list(probes), unstamped[0]


def check_clock(config: Config, bus: ZenohBus, endpoint: str, timeout_s: float = 2.0) -> Item:
    """The router's clock against this machine's, from probes through it (a second session hears them)."""
    name = "clock offset to edge"
    try:
        receiver = open_bus(config.zenoh, Role.DRONE, connect=[endpoint], client=True)
    except DynqosError as exc:
        return Item(name, False, f"a second session to the router failed: {str(exc)[:120]}")
    try:
        probes, unstamped = probe_clock(
            bus.session, receiver.session, clock_probe(config.drone.id), timeout_s
        )
    finally:
        receiver.close()
    found = clock_offset.estimate(probes)
    if found is None:
        why = (
            "the router stamps no samples (zenoh timestamping is off there)"
            if unstamped
            else f"no probe came back through the router in {timeout_s:g} s (its access control?)"
        )
        return Item(name, False, why)
    detail = (
        f"{found.offset_ms:+.1f} ms +- {found.error_ms:.1f} ms to the router's clock "
        f"(need within {clock_offset.MAX_OFFSET_MS:g}; run NTP or chrony on both)"
    )
    return Item(name, abs(found.offset_ms) <= clock_offset.MAX_OFFSET_MS, detail)


def check_qos(config: Config) -> Item:
    cfg = config.onboard
    what = {
        "dynamic": "the supervisor chooses the flow",
        "default": "default flow only",
        "priority": "priority flow only",
    }[cfg.qos]
    return Item(
        "QoS", True, f"qos = {cfg.qos}: {what}; command watchdog {config.supervisor.watchdog_s * 1000:.0f} ms"
    )


def check_unit(systemd_root: Path = Path("/run/systemd/system")) -> Item:
    """The systemd unit's state where systemd runs; a unit not installed (a lab machine, the daemon
    started by hand) is said, not failed; a unit that failed is a failure."""
    if not systemd_root.is_dir() or shutil.which("systemctl") is None:  # sd_booted(): systemd is not PID 1
        return Item("systemd unit", True, "systemd is not running here: the daemon is started by hand")

    def systemctl(verb: str) -> str:
        done = subprocess.run(
            ["systemctl", verb, UNIT], capture_output=True, text=True, timeout=10, check=False
        )
        return done.stdout.strip()

    enabled = systemctl("is-enabled")
    if not enabled:
        return Item("systemd unit", True, f"{UNIT} is not installed: the daemon is started by hand")
    state = systemctl("is-active")
    return Item("systemd unit", state != "failed", f"{UNIT}: {state}, {enabled}")


def check_tasks(config: Config) -> list[Item]:
    """Each of [onboard] tasks: its module loads and declares an Onboard (docs/offload.md); what it
    declares, so that a person sees the rate and deadline the drone will hold it to."""
    from dynqos.common.tasks import Onboard, TaskError, load

    items = []
    for target in config.onboard.tasks:
        try:
            task = load(target, Onboard).task
        except TaskError as exc:
            items.append(Item(f"task {target.rpartition(':')[0][-17:]}", False, str(exc)[:400]))
            continue
        detail = f"{target}: {task.rate_hz:g} Hz, deadline {task.deadline_s * 1000:g} ms, {task.flow} flow"
        items.append(Item(f"task {task.name}", True, detail))
    return items


def run(config: Config, measure_s: float) -> int:
    items = [
        *check_fc(config, measure_s),
        check_camera(config, measure_s),
        *check_router(config),
        check_qos(config),
        *check_tasks(config),
    ]
    items.append(check_unit())
    for item in items:
        print(item.line(), flush=True)
    failed = [i.name for i in items if not i.ok]
    print(
        f"{'all' if not failed else len(items) - len(failed)} of {len(items)} passed"
        + (f"; failed: {', '.join(failed)}" if failed else "")
    )
    return 0 if not failed else 1
