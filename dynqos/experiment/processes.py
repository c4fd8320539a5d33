"""The experiment's processes: `dynqos` subcommands started on free loopback ports, each with its own
log, stopped in reverse order by their own pids (never by name: other processes on the machine are not
ours to end), a layer at a time: the processes started `together` stop together. Used by the scenario
runner, the fault injector and the benchmarks."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import random
import selectors
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

from dynqos.common.config import environment_overrides
from dynqos.common.errors import DynqosError


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def free_ports(count: int, kind: int = socket.SOCK_STREAM) -> list[int]:
    """`count` distinct ports free right now: each socket stays bound until all are chosen, so the kernel
    cannot hand the same port out twice (two free_port() calls can, and two flows on one port is a
    config error)."""
    socks: list[socket.socket] = []
    try:
        for _ in range(count):
            sock = socket.socket(socket.AF_INET, kind)
            socks.append(sock)
            sock.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for sock in socks:
            sock.close()


class FlowPorts(TypedDict):
    default_port: int
    priority_port: int


def flow_ports() -> FlowPorts:
    """The router's two flow ports, distinct and free: ZenohConfig(**flow_ports())."""
    default, priority = free_ports(2)
    return {"default_port": default, "priority_port": priority}


def cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) a live process has used, its threads included (/proc/PID/stat)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()  # after the command name, which may hold spaces
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


EPHEMERAL_PORTS_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
EPHEMERAL_FALLBACK = (32768, 60999)  # Linux's default, where the file cannot be read
LOWEST_UDP_PORT = 10000  # below this: the well-known and registered services' ports


def ephemeral_ports(path: Path = EPHEMERAL_PORTS_FILE) -> tuple[int, int]:
    """The kernel's range for a socket bound to port 0 (ip_local_port_range), inclusive."""
    try:
        low, high = (int(part) for part in path.read_text().split())
    except (OSError, ValueError):
        return EPHEMERAL_FALLBACK
    return low, high


def free_udp_block(
    count: int, *, ephemeral: tuple[int, int] | None = None, rng: random.Random | None = None
) -> int:
    """The first of `count` consecutive free UDP ports on 127.0.0.1 (the drones' offboard ports, then
    the ground station's), outside the kernel's ephemeral range. A port drawn from that range is free
    only until someone binds port 0: a fleet's vehicle binds its own end so, before the daemon it talks
    to has bound the port chosen for it, and once got that very port, then talked to itself and its
    drone never flew (CI, 2026-11-27: 'ignored': 469 at the vehicle, no heartbeat at the daemon). Where
    the range leaves no room (it covers 10000..65535), any free block, as before."""
    low, high = ephemeral or ephemeral_ports()
    spans = [(a, b) for a, b in ((LOWEST_UDP_PORT, low - count), (high + 1, 65536 - count)) if a <= b]
    rng = rng or random.Random()
    for _ in range(200):
        if spans:
            start, end = rng.choice(spans)
            base = rng.randint(start, end)
        else:
            base = free_port(socket.SOCK_DGRAM)
            if base + count > 65536:
                continue
        socks: list[socket.socket] = []
        try:
            for port in range(base, base + count):
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(sock)
                sock.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for sock in socks:
                sock.close()
    raise DynqosError(f"no {count} consecutive free UDP ports on 127.0.0.1")


@dataclass(frozen=True)
class ResidentMemory:
    """A process's resident memory in kB. `rss_kb` (VmRSS) also counts the pages of the shared libraries
    it has mapped, which vary with how fresh the installation is; `anon_kb` (RssAnon) is the memory the
    process itself allocated, where a leak would show."""

    rss_kb: int
    anon_kb: int


def resident_memory(pid: int) -> ResidentMemory | None:
    fields: dict[str, int] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            name, _, value = line.partition(":")
            if name in ("VmRSS", "RssAnon"):
                fields[name] = int(value.split()[0])
    except (OSError, ValueError, IndexError):
        return None
    if "VmRSS" not in fields:
        return None
    return ResidentMemory(rss_kb=fields["VmRSS"], anon_kb=fields.get("RssAnon", fields["VmRSS"]))


def child_environment(environ: Mapping[str, str]) -> dict[str, str]:
    """The environment of a process the runner starts: without DYNQOS_<SECTION>__<KEY> settings, which
    the runner has already folded into the config file it hands the process (a fleet drone's own
    `drone.id` must not be overridden by the one the user set for the run)."""
    settings = {name for name, _ in environment_overrides(environ)}
    return {name: value for name, value in environ.items() if name not in settings}


class Processes:
    """The scenario's processes, started in order, stopped in reverse, each by its own pid. The processes
    one `together` started are one layer, stopped at once: none of them needs another of them."""

    def __init__(self, config: Path, logs: Path, metrics_base: int = 0) -> None:
        self.config = config
        self.logs = logs
        self.metrics_base = metrics_base  # each service's /metrics on base, base + 1, ... (0: off)
        self.metrics_ports: dict[str, int] = {}
        self.procs: dict[str, subprocess.Popen[str]] = {}
        self.info: dict[str, dict[str, Any]] = {}
        self.started: dict[str, tuple[list[str], list[str] | None, Path | None]] = {}
        self.down: set[str] = set()  # killed on purpose (a fault), not a failure
        self.exe = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")
        self._batch: list[tuple[str, subprocess.Popen[str], float]] | None = None  # inside `together`
        self._next_layer = itertools.count()  # layers in start order
        self._batch_layer = 0
        self.layers: dict[str, int] = {}  # each name's layer, from its first start: the order they stop in
        self.launches = 0  # processes launched so far, restarts included

    @contextlib.contextmanager
    def together(self) -> Iterator[None]:
        """Inside, `start` launches a process without waiting for it; at the end each one launched is
        waited for, in order. For processes that need only what is up already: they import and connect
        at the same time (a flight's edge services are up in about half the time)."""
        batch: list[tuple[str, subprocess.Popen[str], float]] = []
        self._batch = batch
        self._batch_layer = next(self._next_layer)
        try:
            yield
        finally:
            self._batch = None
        for name, proc, timeout_s in batch:
            self.info[name] = self._ready(name, proc, timeout_s)

    def start(
        self,
        name: str,
        args: list[str],
        timeout_s: float = 30.0,
        program: list[str] | None = None,
        config: Path | None = None,
        stop_with: str | None = None,
    ) -> dict[str, Any]:
        """Start `dynqos ARGS --config FILE` (or `PROGRAM ARGS --config FILE`), wait for its ready line
        (inside `together`: later, and {} now). FILE is the scenario's config, or `config` (a fleet's
        drone has its own). `stop_with`: a process already started whose layer this one joins (a
        fleet's drones start one by one and stop at once)."""
        err = (self.logs / f"{name}.log").open("a" if name in self.started else "w")  # a restart appends
        if name not in self.layers:
            if stop_with is not None:
                self.layers[name] = self.layers[stop_with]
            elif self._batch is not None:
                self.layers[name] = self._batch_layer
            else:
                self.layers[name] = next(self._next_layer)
        self.started[name] = (args, program, config)
        args = args + self._metrics_option(name, args)
        proc = subprocess.Popen(
            [*(program or [self.exe]), *args, "--config", str(config or self.config)],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            start_new_session=True,
            env=child_environment(os.environ),
        )
        err.close()
        self.procs[name] = proc
        self.launches += 1
        if self._batch is not None:
            self._batch.append((name, proc, timeout_s))
            return {}
        self.info[name] = info = self._ready(name, proc, timeout_s)
        return info

    def _ready(self, name: str, proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
        """The process's ready line (its JSON), or a DynqosError with the end of its log."""
        assert proc.stdout is not None
        with selectors.DefaultSelector() as selector:
            selector.register(proc.stdout, selectors.EVENT_READ)
            line = proc.stdout.readline() if selector.select(timeout=timeout_s) else ""
        if not line:
            raise DynqosError(f"{name} did not start: {self.tail(name)}")
        info: dict[str, Any] = json.loads(line)
        return info

    def _metrics_option(self, name: str, args: list[str]) -> list[str]:
        """`--metrics-port P` for a long-running service when metrics are on; the map of ports is kept in
        logs/metrics.json for whoever scrapes them (docs/observability.md)."""
        if not self.metrics_base or not (args[0] in ("edge", "onboard") or args[:2] == ["sim", "cell"]):
            return []
        port = self.metrics_ports.setdefault(name, self.metrics_base + len(self.metrics_ports))
        # Replaced whole (write aside, then rename): a scraper reading it mid-write saw an empty file.
        tmp = self.logs / "metrics.json.tmp"
        tmp.write_text(json.dumps(self.metrics_ports, indent=1) + "\n")
        tmp.replace(self.logs / "metrics.json")
        return ["--metrics-port", str(port)]

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

    def stop(self, name: str) -> int | None:
        """SIGTERM our own child by its pid and wait for it (a clean stop, not a fault)."""
        self.down.add(name)
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        return self._reaped(proc)

    def restart(self, name: str) -> None:
        args, program, config = self.started[name]
        self.start(name, args, program=program, config=config)
        self.down.discard(name)

    def _px4_pid(self, name: str) -> int | None:
        """The pid of the PX4 our child `name` started (`px4_pid` in its ready line), if it runs one."""
        pid = self.info.get(name, {}).get("px4_pid")
        return pid if isinstance(pid, int) else None

    def signal(self, name: str, signum: int) -> None:
        """`signum` to our child `name`, or to the PX4 it started and runs (`px4_pid` in its ready line):
        a fault that pauses the vehicle pauses PX4 itself, not its wrapper."""
        proc = self.procs[name]
        if proc.poll() is None:
            if (px4 := self._px4_pid(name)) is not None:
                os.kill(px4, signum)
            else:
                proc.send_signal(signum)

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds each process still running has used so far (read before they are stopped)."""
        out = {}
        for name, proc in self.procs.items():
            if proc.poll() is None and (used := cpu_s(proc.pid)) is not None:
                out[name] = round(used, 2)
            px4 = self._px4_pid(name)  # the PX4 it runs (not counted in its own)
            if px4 is not None and (used := cpu_s(px4)) is not None:
                out[f"{name}-px4"] = round(used, 2)
        return out

    def stop_all(self) -> dict[str, int | None]:
        """Stop every process, the last layer first: SIGCONT (in case a fault paused it, or the PX4 it
        runs) and SIGTERM to each one of a layer, then wait for each. Their exit codes."""
        codes: dict[str, int | None] = {}
        for layer in sorted(set(self.layers.values()), reverse=True):
            names = [name for name in reversed(list(self.procs)) if self.layers[name] == layer]
            for name in names:
                proc = self.procs[name]
                if proc.poll() is None:
                    proc.send_signal(signal.SIGCONT)
                    if (px4 := self._px4_pid(name)) is not None:
                        with contextlib.suppress(OSError):
                            os.kill(px4, signal.SIGCONT)
                    proc.send_signal(signal.SIGTERM)
            for name in names:
                codes[name] = self._reaped(self.procs[name])
        return codes

    @staticmethod
    def _reaped(proc: subprocess.Popen[str]) -> int | None:
        """Wait for a process told to stop, killing it after 15 s; its exit code."""
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
        if proc.stdout is not None:
            proc.stdout.close()
        return proc.returncode
