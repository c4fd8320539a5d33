"""`dynqos demo` and `dynqos run FILE`: the paper's experiment end to end on one machine.

For each scenario: start the router, the cell emulator, the simulator, the planner, the MPC, the
detector and the onboard daemon as real processes with a generated config (free ports on 127.0.0.1);
wait until the drone offloads; fly for `duration_s`, switching the cell's background load on at
`bg_start_s` through the cell's control API; record what a ground station would see (states,
references, supervisor status, cell counters); stop every process (also on Ctrl-C or when any of them
dies, naming it); write the run folder (see dynqos/report.py).
"""

from __future__ import annotations

import json
import logging
import math
import selectors
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from dynqos.common import keys
from dynqos.common.config import OnboardConfig, ZenohConfig, build
from dynqos.common.errors import ConfigError, DynqosError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Reference, State, SupervisorStatus
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Received, Role, open_bus
from dynqos.faults import Fault, FaultInjector, FaultWindow

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

log = logging.getLogger(__name__)

DEFAULT_SCENARIOS = ("baseline", "bg-noqos", "bg-dynqos", "bg-staticqos")


@dataclass(frozen=True, slots=True, kw_only=True)
class Scenario:
    name: str
    description: str = ""
    mission: Literal["circle", "hover", "figure8"] = "circle"
    qos: Literal["dynamic", "default", "priority"] = "dynamic"
    duration_s: float = 30.0  # flight time recorded after offloading starts
    bg_start_s: float = 15.0  # seconds into the recorded flight; negative: no background load
    bg_mbps: float = 80.0
    uav_mbps: float = 47.0  # what the drone's camera is sized to offer (before scale)
    scale: float = 10.0
    seed: int = 0
    settle_s: float = 4.0  # excluded from the baseline statistics after offloading starts
    camera_fps: float = 15.0
    # The camera's bytes are paced at this rate (before scale; 0: each image in one burst): above what
    # the drone offers, below what the priority bearer drains under load (81.3 x 4/5 = 65 Mbit/s).
    camera_pace_mbps: float = 62.0
    wind_mps: float = 0.5  # a steady breeze from the north...
    gust_std_mps: float = 0.5  # ...with gusts, so that control delay shows in the tracking
    gust_tau_s: float = 0.5  # short gusts: many per window, so windows compare alike (docs/demo.md)
    base_delay_ms: float = 5.0  # one way: with processing and camera head-of-line ~15 ms C&C RTT, below rho2
    faults: tuple[Fault, ...] = ()  # injected during the flight (dynqos/faults.py, docs/reliability.md)
    memory_sample_s: float = 5.0  # how often each process's resident memory is recorded

    def __post_init__(self) -> None:
        if not 5 <= self.duration_s <= 3600:
            raise ConfigError("duration_s", "must be in 5..3600 s")
        if self.bg_start_s >= self.duration_s:
            raise ConfigError("bg_start_s", "must be before the end of the run (or negative for none)")
        if not 0 <= self.bg_mbps <= 1e5 or not 0.1 <= self.uav_mbps <= 1e5:
            raise ConfigError("bg_mbps", "rates must be in 0..100000 Mbit/s")
        if not 0.01 <= self.scale <= 1000:
            raise ConfigError("scale", "must be in 0.01..1000")
        if not 0 <= self.camera_pace_mbps <= 1e5:
            raise ConfigError("camera_pace_mbps", "must be in 0..100000 Mbit/s (0: no pacing)")
        for i, fault in enumerate(self.faults):
            if fault.at_s + fault.duration_s > self.duration_s:
                raise ConfigError(f"faults[{i}].at_s", "the fault must end before the run does")
        if not 0.5 <= self.memory_sample_s <= 600:
            raise ConfigError("memory_sample_s", "must be in 0.5..600 s")


def load_scenario(path: str | Path) -> Scenario:
    source = str(path)
    try:
        table = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("", "scenario file not found", source=source) from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError("", f"cannot read scenario ({exc})", source=source) from None
    unknown = set(table) - {"scenario"}
    if unknown or not isinstance(table.get("scenario"), dict):
        raise ConfigError(
            ", ".join(sorted(unknown)) or "scenario",
            "a scenario file has one [scenario] table",
            source=source,
        )
    try:
        return build(Scenario, table["scenario"], "scenario")
    except ConfigError as exc:
        raise exc.with_source(source) from None


def builtin_scenario(name: str) -> Scenario:
    files = resources.files("dynqos") / "scenarios"
    path = files / f"{name}.toml"
    if not path.is_file():
        known = sorted(p.name.removesuffix(".toml") for p in files.iterdir() if p.name.endswith(".toml"))
        raise ConfigError("--scenario", f"unknown scenario {name!r} (known: {', '.join(known)})")
    with resources.as_file(path) as real:
        return load_scenario(real)


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def camera_size_for(target_bps: float, fps: float, part_bytes: int = 0) -> tuple[int, int]:
    """An image size whose RGB-D frames (JPEG + zstd16, in parts of `part_bytes` when paced) at `fps`
    offer about target_bps, message headers included.

    Scaling the experiment down must shrink the frames, not the frame rate: a frame's serialisation time
    through the scaled cell then stays what it is at full scale, and so do the latencies it causes.
    Small images compress worse per pixel, so the size found by area is measured and corrected twice.
    """
    width = 640
    for _ in range(3):
        linear = math.sqrt(target_bps / fps / _frame_bits(width, width * 3 // 4, part_bytes))
        width = max(64, min(1280, round(width * linear / 4) * 4))
    return width, width * 3 // 4


def _frame_bits(width: int, height: int, part_bytes: int = 0) -> float:
    """Mean size of one RGB-D frame on the wire, seen from the demo's circle (radius 2 m, yaw along it,
    tilted 0.06 rad as a drone flying it in a breeze: the floor in view adds about 5%)."""
    from dynqos.onboard.camera import SimCamera, encode_depth, encode_rgb
    from dynqos.onboard.pacing import FRAME_HEADER_BYTES
    from dynqos.sim.world import default_world

    camera = SimCamera(default_world(), width, height)  # the onboard camera's optics
    tilt = 0.06
    total = 0.0
    views = 6
    for k in range(views):
        theta = 2 * math.pi * k / views
        yaw = theta + math.pi / 2
        position = (2.0 * math.cos(theta), 2.0 * math.sin(theta), -1.5)
        raw = camera.grab((position, _quaternion(yaw, tilt, tilt)))
        assert raw is not None
        assert raw.depth_m is not None
        for data in (encode_rgb(raw.rgb, 90), encode_depth(raw.depth_m)):
            messages = math.ceil(len(data) / part_bytes) if part_bytes else 1
            total += 8.0 * (len(data) + messages * FRAME_HEADER_BYTES)
    return total / views


def _quaternion(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


# ---- processes ----------------------------------------------------------------------------------------


class Processes:
    """The scenario's processes, started in order, stopped in reverse, each by its own pid."""

    def __init__(self, config: Path, logs: Path) -> None:
        self.config = config
        self.logs = logs
        self.procs: dict[str, subprocess.Popen[str]] = {}
        self.info: dict[str, dict[str, Any]] = {}
        self.started: dict[str, tuple[list[str], list[str] | None]] = {}
        self.down: set[str] = set()  # killed on purpose (a fault), not a failure
        self.exe = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")

    def start(
        self, name: str, args: list[str], timeout_s: float = 30.0, program: list[str] | None = None
    ) -> dict[str, Any]:
        """Start `dynqos ARGS --config FILE` (or `PROGRAM ARGS --config FILE`), wait for its ready line."""
        err = (self.logs / f"{name}.log").open("a" if name in self.started else "w")  # a restart appends
        self.started[name] = (args, program)
        proc = subprocess.Popen(
            [*(program or [self.exe]), *args, "--config", str(self.config)],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            start_new_session=True,
        )
        err.close()
        self.procs[name] = proc
        assert proc.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(proc.stdout, selectors.EVENT_READ)
            line = proc.stdout.readline() if selector.select(timeout=timeout_s) else ""
        if not line:
            raise DynqosError(f"{name} did not start: {self.tail(name)}")
        info: dict[str, Any] = json.loads(line)
        self.info[name] = info
        return info

    def tail(self, name: str, lines: int = 3) -> str:
        path = self.logs / f"{name}.log"
        text = path.read_text(errors="replace").strip().splitlines() if path.exists() else []
        return " | ".join(text[-lines:]) or "(no output)"

    def dead(self) -> list[str]:
        """Processes that exited, except those a fault stopped on purpose."""
        return [
            name for name, proc in self.procs.items() if proc.poll() is not None and name not in self.down
        ]

    def kill(self, name: str) -> None:
        """SIGKILL our own child by its pid (a crash, as far as everyone else can tell)."""
        self.down.add(name)
        proc = self.procs[name]
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()

    def restart(self, name: str) -> None:
        args, program = self.started[name]
        self.start(name, args, program=program)
        self.down.discard(name)

    def signal(self, name: str, signum: int) -> None:
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signum)

    def stop_all(self) -> dict[str, int | None]:
        codes: dict[str, int | None] = {}
        for name in reversed(list(self.procs)):
            proc = self.procs[name]
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)  # in case a fault paused it
                proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5)
            if proc.stdout is not None:
                proc.stdout.close()
            codes[name] = proc.returncode
        return codes


# ---- recording ----------------------------------------------------------------------------------------


@dataclass
class Recording:
    t0_ns: int = 0
    states: list[tuple[float, State]] = field(default_factory=list)  # (uplink latency ms, state)
    refs: list[Reference] = field(default_factory=list)
    status: list[SupervisorStatus] = field(default_factory=list)
    cell: list[dict[str, Any]] = field(default_factory=list)
    bg_on_ns: int | None = None
    offload_ns: int | None = None
    faults: list[FaultWindow] = field(default_factory=list)
    memory_kb: dict[str, list[tuple[float, int]]] = field(default_factory=dict)  # name -> (t_s, RSS kB)


def _rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError):
        return None
    return None


def _get_json(port: int, path: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        data: dict[str, Any] = json.loads(response.read())
        return data


def _post_json(port: int, path: str, body: dict[str, Any]) -> dict[str, Any]:
    request = urllib.request.Request(
        f"http://127.0.0.1:{port}{path}",
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Content-Type": "application/json"},
    )
    with urllib.request.urlopen(request, timeout=5) as response:
        data: dict[str, Any] = json.loads(response.read())
        return data


def run_scenario(  # noqa: C901, PLR0915 (the scenario in order; see issue notes)
    scenario: Scenario, out: Path, *, stop: threading.Event | None = None, progress: bool = True
) -> dict[str, Any]:
    """Run one scenario into out/<name>/ and return its summary."""
    from dynqos.report import summarise, write_scenario

    stop = stop or threading.Event()
    folder = out / scenario.name
    folder.mkdir(parents=True, exist_ok=True)
    logs = folder / "logs"
    logs.mkdir(exist_ok=True)
    zcfg = ZenohConfig(default_port=free_port(), priority_port=free_port())
    api = free_port(socket.SOCK_DGRAM)
    fps = scenario.camera_fps
    part_bytes = OnboardConfig().camera_part_bytes if scenario.camera_pace_mbps > 0 else 0
    width, height = camera_size_for(scenario.uav_mbps * 1e6 / scenario.scale, fps, part_bytes)
    config = folder / "dynqos.toml"
    config.write_text(f"""# generated by dynqos demo for scenario {scenario.name}
[drone]
id = "uav1"
[zenoh]
default_port = {zcfg.default_port}
priority_port = {zcfg.priority_port}
[supervisor]
seed = {scenario.seed}
[cell]
scale = {scenario.scale}
ue_buffer_bytes = {max(1500, round(1_000_000 / scenario.scale))}
base_delay_up_ms = {scenario.base_delay_ms}
base_delay_down_ms = {scenario.base_delay_ms}
control_port = 0
default_listen_port = 0
priority_listen_port = 0
seed = {scenario.seed}
[vehicle]
wind_mps = [{scenario.wind_mps}, 0.0, 0.0]
gust_std_mps = {scenario.gust_std_mps}
gust_tau_s = {scenario.gust_tau_s}
offboard_bind_port = 0
gcs_bind_port = 0
offboard_remote_port = {api}
gcs_remote_port = {free_port(socket.SOCK_DGRAM)}
seed = {scenario.seed}
[planner]
mission = "{scenario.mission}"
lead_in_s = 2
[onboard]
mavlink_url = "udpin:127.0.0.1:{api}"
qos = "{scenario.qos}"
camera_fps = {fps:.2f}
camera_pace_mbps = {scenario.camera_pace_mbps / scenario.scale:.6g}
camera_width = {width}
camera_height = {height}
# The heading stays the FC's own, as in every run the README quotes. Flown along the circle, the camera
# sees the pillars for most of a lap (measured: the baseline in q2, high risk, 22 of 30 s) and the
# scenarios' contrast changes; docs/demo.md says more.
yaw = "free"
""")
    procs = Processes(config, logs)
    rec = Recording()
    ok = True
    failure = ""
    try:
        procs.start("router", ["edge", "router"])
        cell = procs.start("cell", ["sim", "cell", "--out", str(folder)])
        cell_port = cell["control_port"]
        bearers = cell["bearers"]
        text = config.read_text() + (
            f'connect_default = "127.0.0.1:{bearers["uav1-default"]["port"]}"\n'
            f'connect_priority = "127.0.0.1:{bearers["uav1-priority"]["port"]}"\n'
        )
        config.write_text(text)
        procs.start("vehicle", ["sim", "vehicle", "--duration", "3600"])
        procs.start("planner", ["edge", "planner"])
        procs.start("mpc", ["edge", "mpc"])
        procs.start("detector", ["edge", "detector"])
        bus = open_bus(zcfg, Role.EDGE)
        try:
            states: BoundedQueue[Received] = BoundedQueue(200_000)
            refs: BoundedQueue[Received] = BoundedQueue(200_000)
            status: BoundedQueue[Received] = BoundedQueue(200_000)
            bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATE), states, expect=(State,))
            bus.subscribe(keys.downlink("uav1", Downlink.REFERENCE), refs, expect=(Reference,))
            bus.subscribe(keys.uplink_any_flow("uav1", Stream.STATUS), status, expect=(SupervisorStatus,))
            procs.start("onboard", ["onboard", "--takeoff"])
            deadline = time.monotonic() + 60
            while rec.offload_ns is None and time.monotonic() < deadline and not stop.is_set():
                item = states.get(0.5)
                if item is not None and isinstance(item.message, State) and item.message.mode == "offboard":
                    rec.offload_ns = item.message.stamp_ns
            if rec.offload_ns is None:
                raise DynqosError(f"the drone never started offloading: {procs.tail('onboard')}")
            rec.t0_ns = rec.offload_ns
            next_poll = next_memory = time.monotonic()
            end = time.monotonic() + scenario.duration_s
            injector = FaultInjector(procs, lambda event: _post_json(cell_port, "/events", event), bus)
            pending = sorted(scenario.faults, key=lambda fault: fault.at_s)
            active: list[FaultWindow] = []
            try:
                while time.monotonic() < end and not stop.is_set():
                    elapsed = scenario.duration_s - (end - time.monotonic())
                    while pending and elapsed >= pending[0].at_s:
                        active.append(injector.begin(pending.pop(0)))
                    for window in [w for w in active if elapsed >= w.fault.at_s + w.fault.duration_s]:
                        injector.end(window)
                        active.remove(window)
                    if time.monotonic() >= next_memory:
                        next_memory += scenario.memory_sample_s
                        for name, proc in procs.procs.items():
                            if (rss := _rss_kb(proc.pid)) is not None and name not in procs.down:
                                rec.memory_kb.setdefault(name, []).append((elapsed, rss))
                    _record_tick(scenario, rec, procs, cell_port, elapsed, progress)
                    if time.monotonic() >= next_poll:
                        next_poll += 0.5
                        counters = _get_json(cell_port, "/counters")
                        counters["now_ns"] = time.monotonic_ns()
                        rec.cell.append(counters)
                    stop.wait(0.1)  # the recorder's sampling period
            finally:
                injector.close()
                rec.faults = injector.windows
            for item in states.drain():
                if isinstance(item.message, State):
                    rec.states.append(((item.arrival_ns - item.message.stamp_ns) / 1e6, item.message))
            rec.refs = [i.message for i in refs.drain() if isinstance(i.message, Reference)]
            rec.status = [i.message for i in status.drain() if isinstance(i.message, SupervisorStatus)]
        finally:
            bus.close()
        if stop.is_set():
            ok, failure = False, "interrupted"
    except DynqosError as exc:
        ok, failure = False, str(exc)
        log.error("scenario %s failed: %s", scenario.name, exc)
    finally:
        codes = procs.stop_all()
        if progress:
            sys.stderr.write("\n")
    if ok and any(code not in (0, -signal.SIGTERM) for code in codes.values()):
        bad = {k: v for k, v in codes.items() if v not in (0, -signal.SIGTERM)}
        ok, failure = False, f"processes exited with errors: {bad}"
    onboard_log = (
        (logs / "onboard.log").read_text(errors="replace") if (logs / "onboard.log").exists() else ""
    )
    summary = summarise(scenario, rec, onboard_log, ok=ok, failure=failure)
    write_scenario(folder, scenario, rec, summary)
    return summary


def _record_tick(
    scenario: Scenario, rec: Recording, procs: Processes, cell_port: int, elapsed: float, progress: bool
) -> None:
    """The recorder's duties each tick: start the background load, fail on a dead process."""
    if scenario.bg_start_s >= 0 and rec.bg_on_ns is None and elapsed >= scenario.bg_start_s:
        _post_json(
            cell_port, "/events", {"kind": "background", "user": "bg", "offered_mbps": scenario.bg_mbps}
        )
        rec.bg_on_ns = time.monotonic_ns()
    dead = procs.dead()
    if dead:
        raise DynqosError(f"{dead[0]} exited during the run: {procs.tail(dead[0])}")
    if progress:
        _progress(scenario, elapsed, rec)


def _progress(scenario: Scenario, elapsed: float, rec: Recording) -> None:
    width = 30
    done = min(width, int(width * elapsed / scenario.duration_s))
    last = rec.cell[-1] if rec.cell else None
    bar = "#" * done + "." * (width - done)
    line = f"\r{scenario.name:<14} [{bar}] {elapsed:5.1f}/{scenario.duration_s:.0f} s"
    if last:
        bearers = last["bearers"]
        delays = max(b["queue_delay_ms"] for b in bearers.values())
        bg = "on" if rec.bg_on_ns else "off"
        line += f"  background {bg}, drone queue {delays:6.1f} ms"
    if sys.stderr.isatty():
        sys.stderr.write(line)
        sys.stderr.flush()


def run_demo(
    names: list[str],
    out: Path,
    *,
    duration_s: float | None,
    scale: float | None,
    seed: int | None,
    scenarios: list[Scenario] | None = None,
) -> dict[str, Any]:
    from dynqos.report import write_report

    chosen = scenarios if scenarios is not None else [builtin_scenario(n) for n in names]
    overrides: dict[str, Any] = {}
    if duration_s is not None:
        overrides["duration_s"] = duration_s
    if scale is not None:
        overrides["scale"] = scale
    if seed is not None:
        overrides["seed"] = seed
    runs = []
    for scenario in chosen:
        if overrides:
            changes = dict(overrides)
            if "duration_s" in changes and scenario.bg_start_s >= 0:
                changes["bg_start_s"] = changes["duration_s"] / 2
            try:
                scenario = replace(scenario, **changes)
            except ConfigError as exc:
                raise exc.under(scenario.name) from None
        runs.append(scenario)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError("--out", f"cannot make the run folder {out}: {exc.strerror or exc}") from None
    stop = threading.Event()
    previous = signal.getsignal(signal.SIGINT)

    def interrupt(signum: int, _frame: object) -> None:
        log.warning("interrupted: stopping every process")
        stop.set()

    signal.signal(signal.SIGINT, interrupt)
    signal.signal(signal.SIGTERM, interrupt)
    summaries = []
    started = time.monotonic()
    try:
        for scenario in runs:
            if stop.is_set():
                break
            log.info("scenario %s: %s", scenario.name, scenario.description)
            summary = run_scenario(scenario, out, stop=stop)
            summaries.append(summary)
            log.info(
                "scenario %s: ok=%s rtt baseline mean %s ms, loaded mean %s ms",
                scenario.name,
                summary["ok"],
                _fmt(summary["rtt_ms"]["baseline"]),
                _fmt(summary["rtt_ms"]["loaded"]),
            )
    finally:
        signal.signal(signal.SIGINT, previous)
    top = {
        "scenarios": summaries,
        "wall_time_s": time.monotonic() - started,
        "out": str(out),
        "ok": bool(summaries) and all(s["ok"] for s in summaries) and len(summaries) == len(runs),
    }
    (out / "summary.json").write_text(json.dumps(top, indent=2) + "\n")
    write_report(out, summaries)
    return top


def _fmt(stats: dict[str, Any] | None) -> str:
    return "-" if not stats or stats.get("mean") is None else f"{stats['mean']:.1f}"


def default_out_dir() -> Path:
    return Path("runs") / time.strftime("%Y%m%d-%H%M%S")
