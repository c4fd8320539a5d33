"""`dynqos sim px4`: a real PX4 SITL (PX4's own flight stack, with its SIH physics or whatever the build
simulates) in place of dynqos's simulated vehicle, as a process the runner starts and stops by its pid.

PX4 numbers its instances as dynqos's vehicle does: instance N has MAVLink system id N+1, sends its
offboard link to 14540+N and listens on 14580+N, and sends its ground-station link to 14550 (these ports
are PX4's own, set by its start-up scripts, so the onboard daemon listens where PX4 sends). Everything
PX4 writes (parameters, dataman, the ULog, a signing key) goes into the instance's working directory,
which the runner puts into the run's folder so that the ULog stays with the run.

A build's `bin/` holds `px4-<module>` links to `bin/px4` that PX4's scripts call through PATH; a copy
that lost its links (plain files) cannot boot, so each instance gets its own `bin/` of links to the one
binary in its working directory. The wrapper copies PX4's console to its log, says ready once PX4's
start-up script returned, and on SIGTERM stops PX4 by its pid (PX4 then shuts down cleanly).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import signal
import socket
import struct
import subprocess
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from dynqos.common import mavsign
from dynqos.common.config import Config, Px4Config
from dynqos.common.errors import DynqosError
from dynqos.common.lifecycle import ready_line, stop_on_signals
from dynqos.sim.vehicle.px4_origin import Home, set_origin

log = logging.getLogger(__name__)

MAX_INSTANCE = 9  # from 10 on PX4 sends every instance's offboard link to 14549
READY_TEXT = "Startup script returned successfully"
FAILED_TEXT = "Startup script returned with return value"
STOP_TIMEOUT_S = 10.0
# What dynqos flies PX4 with (docs/px4.md): no joystick, so on offboard loss Land (the manual modes
# PX4 takes by default need one, and without it PX4 would Return); manual-control loss never applies
# to offboard; the ground-station link is not dynqos's, so its loss does nothing.
DYNQOS_PARAMETERS: dict[str, float] = {
    "COM_OBL_RC_ACT": 4,  # offboard loss: Land
    "COM_RCL_EXCEPT": 4,  # manual-control loss ignored in Offboard
    "NAV_DLL_ACT": 0,  # ground-station datalink loss: nothing
    "COM_OF_LOSS_T": 1.0,  # setpoints silent for 1 s: offboard lost (PX4's default, said aloud)
}


@dataclass(frozen=True, slots=True)
class Px4Ports:
    """PX4 SITL's UDP ports of instance N (its start-up script px4-rc.mavlink sets them)."""

    instance: int

    @property
    def system_id(self) -> int:
        return self.instance + 1

    @property
    def offboard_remote(self) -> int:  # where PX4 sends the offboard link: the onboard daemon listens
        return 14540 + self.instance

    @property
    def offboard_local(self) -> int:
        return 14580 + self.instance

    @property
    def gcs_remote(self) -> int:
        return 14550

    @property
    def gcs_local(self) -> int:
        return 18570 + self.instance

    def bound(self) -> tuple[int, ...]:
        """The UDP ports PX4 itself binds (offboard, ground station, payload, gimbal, SIH display)."""
        i = self.instance
        return (14580 + i, 18570 + i, 14280 + i, 13030 + i, 19450 + i)


def px4_folder(directory: str) -> Path:
    """PX4's folder as `[px4] dir` names it, checked: one line saying what is wrong, never a traceback."""
    if not directory:
        raise DynqosError(
            "no PX4 folder: set [px4] dir (or DYNQOS_PX4__DIR, or --px4-dir) to a folder with bin/px4 and "
            "etc/, such as PX4's build/px4_sitl_default after `make px4_sitl` (docs/px4.md)"
        )
    folder = Path(directory).expanduser().resolve()
    binary, scripts = folder / "bin" / "px4", folder / "etc" / "init.d-posix" / "rcS"
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        raise DynqosError(f"[px4] dir {folder}: no executable bin/px4 there (a PX4 SITL build's folder)")
    if not scripts.is_file():
        raise DynqosError(f"[px4] dir {folder}: no etc/init.d-posix/rcS there (a PX4 SITL build's folder)")
    return folder


def event_catalogue(folder: Path) -> Path | None:
    """PX4's event catalogue in its folder: `events/` in a build of PX4's tree, `etc/extras/` in a
    packaged SITL (the onboard daemon reads PX4's events with it, onboard/px4_events.py)."""
    for candidate in (
        folder / "events" / "all_events.json.xz",
        folder / "etc" / "extras" / "all_events.json.xz",
    ):
        if candidate.is_file():
            return candidate
    return None


def instance_locked(instance: int) -> bool:
    """Whether a PX4 instance runs with this number: PX4 holds a lock on /tmp/px4_lock-<N> while it does."""
    path = Path(f"/tmp/px4_lock-{instance}")
    if not path.exists():
        return False
    try:
        with path.open("a") as lock:
            fcntl.lockf(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.lockf(lock, fcntl.LOCK_UN)
    except OSError:
        return True
    return False


def udp_free(port: int, host: str = "127.0.0.1") -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((host, port))
        except OSError:
            return False
    return True


def free_instances(count: int) -> list[int]:
    """`count` instance numbers that no PX4 runs as and whose ports (PX4's and the onboard daemon's) are
    free now, lowest first: a fleet's PX4 instances, or one drone's."""
    found = []
    for instance in range(MAX_INSTANCE + 1):
        ports = Px4Ports(instance)
        if instance_locked(instance) or not all(udp_free(p) for p in (*ports.bound(), ports.offboard_remote)):
            continue
        found.append(instance)
        if len(found) == count:
            return found
    raise DynqosError(
        f"no {count} free PX4 SITL instance(s) among 0..{MAX_INSTANCE}: another PX4 or program holds their "
        "ports 14540+N, 14580+N, 18570+N (stop it, or fly fewer drones)"
    )


def boot_environment(cfg: Px4Config, instance: int, environ: Mapping[str, str]) -> dict[str, str]:
    """PX4's environment: the SIH quadrotor unless the caller chose an airframe, and the parameters at
    boot (PX4_PARAM_<NAME>: dynqos's, then `[px4] params` over them)."""
    env = {k: v for k, v in environ.items() if not k.startswith("PX4_PARAM_")}
    if "PX4_SYS_AUTOSTART" not in env:
        env.setdefault("PX4_SIM_MODEL", "sihsim_quadx")
    params = {**DYNQOS_PARAMETERS, **({} if cfg.ulog else {"SDLOG_BACKEND": 0}), **cfg.params}
    for name, value in params.items():
        env[f"PX4_PARAM_{name}"] = f"{value:g}"
    return env


def private_bin(folder: Path, workdir: Path) -> Path:
    """<workdir>/bin: `px4` and a `px4-<module>` link to PX4's one binary for every module the build has,
    and its px4-alias.sh; PX4 puts this folder on its PATH (the folder of the binary it was started as)."""
    binary = folder / "bin" / "px4"
    own = workdir / "bin"
    own.mkdir(parents=True, exist_ok=True)
    for entry in (folder / "bin").iterdir():
        target = own / entry.name
        if target.is_symlink() or target.exists():
            target.unlink()
        if entry.name.endswith(".sh"):
            target.write_bytes(entry.read_bytes())
        elif entry.name == "px4" or entry.name.startswith("px4-"):
            target.symlink_to(binary)
    return own / "px4"


class Px4Process:
    """One PX4 instance started in `workdir`, its console copied to `console`."""

    def __init__(
        self, folder: Path, instance: int, workdir: Path, env: dict[str, str], console: Path
    ) -> None:
        self.instance = instance
        self.workdir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        program = private_bin(folder, workdir)
        self.ready = threading.Event()
        self.failed = ""
        self._console = console.open("w")
        try:
            self.proc = subprocess.Popen(
                [str(program), "-d", "-w", str(workdir), "-i", str(instance), str(folder / "etc")],
                cwd=workdir,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                errors="replace",
            )
        except OSError as exc:
            self._console.close()
            raise DynqosError(f"cannot start {program}: {exc.strerror or exc}") from None
        self._reader = threading.Thread(target=self._copy_console, name="px4-console", daemon=True)
        self._reader.start()

    def _copy_console(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._console.write(line)
            self._console.flush()
            if READY_TEXT in line:
                self.ready.set()
            elif FAILED_TEXT in line:
                self.failed = line.strip()
                self.ready.set()
        self.ready.set()  # PX4 exited: whoever waits finds out by its return code

    def wait_ready(self, timeout_s: float) -> None:
        if not self.ready.wait(timeout_s):
            raise DynqosError(f"PX4 instance {self.instance} did not finish its start-up in {timeout_s:g} s")
        if self.failed or self.proc.poll() is not None:
            why = self.failed or f"exited with {self.proc.returncode}"
            raise DynqosError(f"PX4 instance {self.instance} failed to start: {why} (see its console log)")

    def stop(self) -> int:
        """SIGTERM to PX4 by its pid (a clean shutdown), SIGKILL if it has not ended in STOP_TIMEOUT_S."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            log.warning("px4: instance %d did not stop in %.0f s; killing it", self.instance, STOP_TIMEOUT_S)
            self.proc.kill()
            code = self.proc.wait(timeout=5)
        self._reader.join(timeout=5)
        self._console.close()
        return code


STATE_FILES = ("parameters.bson", "parameters_backup.bson", "dataman", "mavlink/mavlink-signing-key.bin")


def forget_state(workdir: Path) -> None:
    """What PX4 kept from a previous boot in `workdir` (parameters, mission data, a signing key) is
    removed, so that every boot starts from the airframe's defaults and this config's parameters; its
    ULogs stay."""
    for name in STATE_FILES:
        (workdir / name).unlink(missing_ok=True)


def install_signing_key(key: bytes, workdir: Path) -> Path:
    """The key where PX4 looks for it at boot (<workdir>/mavlink/mavlink-signing-key.bin: the 32-byte key,
    then the last timestamp as a little-endian uint64, here now's), owner-only."""
    path = workdir / "mavlink" / "mavlink-signing-key.bin"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(key + struct.pack("<Q", mavsign.timestamp_now()))
    path.chmod(0o600)
    return path


def ulogs(workdir: Path) -> list[Path]:
    """The ULog files PX4 wrote in its working directory, oldest first."""
    return sorted((workdir / "log").glob("**/*.ulg"))


def run(config: Config, *, instance: int, workdir: Path, start_m: tuple[float, float] = (0.0, 0.0)) -> int:
    """Boot PX4 instance `instance` in `workdir` standing at `start_m` (north, east) of the fleet's common
    origin, say ready, and run until SIGTERM or PX4's own exit."""
    if not 0 <= instance <= MAX_INSTANCE:
        raise DynqosError(f"--instance must be in 0..{MAX_INSTANCE}, got {instance}")
    folder = px4_folder(config.px4.dir)
    if instance_locked(instance):
        raise DynqosError(f"PX4 instance {instance} is already running (/tmp/px4_lock-{instance} is locked)")
    workdir = workdir.resolve()
    forget_state(workdir)
    env = boot_environment(config.px4, instance, os.environ)
    origin = Home.of(env)
    env.update(origin.shifted(start_m).environment())
    key = mavsign.load_key(config.px4.signing_key) if config.px4.signing_key else None
    if key is not None:
        install_signing_key(key, workdir)
    px4 = Px4Process(folder, instance, workdir, env, workdir / "console.log")
    stop, stopped_by_signal = threading.Event(), threading.Event()

    def on_signal() -> None:
        stopped_by_signal.set()
        stop.set()

    stop_on_signals("px4", on_signal)
    try:
        px4.wait_ready(config.px4.boot_timeout_s)
        ports = Px4Ports(instance)
        if start_m != (0.0, 0.0):
            set_origin(ports, origin, start_m, key, config.px4.boot_timeout_s)
        ready_line(
            "px4",
            px4_pid=px4.proc.pid,
            instance=instance,
            system_id=ports.system_id,
            workdir=str(workdir),
            offboard={"remote": ports.offboard_remote, "bind": ports.offboard_local},
            gcs={"remote": ports.gcs_remote, "bind": ports.gcs_local},
            folder=str(folder),
            signing="on" if config.px4.signing_key else "off",
            start_m=list(start_m),
        )
        log.info("px4: instance %d (pid %d) is up in %s", instance, px4.proc.pid, workdir)

        def on_exit() -> None:
            px4.proc.wait()
            stop.set()

        threading.Thread(target=on_exit, name="px4-exit", daemon=True).start()
        stop.wait()  # a signal or PX4's own exit, whichever comes first
    finally:
        died = px4.proc.poll() is not None and not stopped_by_signal.is_set()
        code = px4.stop()
        with contextlib.suppress(OSError):
            log.info(
                "px4: instance %d stopped (exit %d); ULogs: %s",
                instance,
                code,
                [str(p.relative_to(workdir)) for p in ulogs(workdir)],
            )
    if died:
        raise DynqosError(f"PX4 instance {instance} exited by itself with {code} (see {workdir}/console.log)")
    return 0
