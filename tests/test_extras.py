"""Each role installs only what it runs, and what it installs starts every process of that role.

`dynqos[onboard]` has no solver and no plotting and runs the onboard daemon; `dynqos[edge]` runs the
router, the MPC, the planner, the detector and the QoS agent with the `camara` backend (the client of
the operator's API, without the emulated operator's schema validator). Each process is started from the
fresh environment until /healthz serves its first periodic health line.

Slow: it builds the wheel once and installs it with its dependencies into fresh virtual environments
(from the package index, or pip's cache after the project's own install), each with no pip of its own.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.conftest import flow_ports_toml, free_tcp_port
from tests.procs import DYNQOS, DynqosProcess
from tests.wheel import build_wheel

HEALTH_WAIT_S = 45.0  # the first periodic line comes after health_interval_s; the rest is start-up

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


def _run(*cmd: str | Path, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """`cmd` from a folder outside the repository, whose dynqos/ would shadow the installed package."""
    return subprocess.run(
        [str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, check=False, cwd="/"
    )


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_wheel(tmp_path_factory.mktemp("wheel"))


def _venv_with(wheel: Path, extra: str, folder: Path) -> Path:
    """A fresh virtual environment with `dynqos[extra]` and nothing else; its bin folder."""
    venv = folder / f"venv-{extra}"
    assert _run(sys.executable, "-m", "venv", "--without-pip", venv).returncode == 0
    _install(venv / "bin" / "python", f"{wheel}[{extra}]")
    return venv / "bin"


def _install(python: Path, requirement: str) -> None:
    """`requirement` into the environment of `python`, by this environment's pip (`pip --python`): the
    fresh one needs no pip of its own. Without byte-compiling: each role compiles what it imports
    when it starts, and an install that compiles every module of numpy, OpenCV and the rest took 42 s
    of the 47 here (12 s without, docs/development.md)."""
    pip = (sys.executable, "-m", "pip", "--python", python, "--disable-pip-version-check")
    installed = _run(*pip, "install", "-q", "--no-compile", requirement)
    assert installed.returncode == 0, installed.stderr[-3000:]


def _absent(python: Path, modules: tuple[str, ...]) -> str:
    found = _run(python, "-c", f"import importlib.util as u; print([m for m in {modules} if u.find_spec(m)])")
    return found.stdout.strip() + found.stderr


def _healthy_line(port: int, deadline: float) -> str:
    """/healthz's body once it serves a periodic health line (not the start-up "ready"), or the last
    answer when the deadline passes."""
    last = "no answer"
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as reply:
                last = reply.read().decode()
            if not last.rstrip().endswith(": ready"):
                return last
        except (urllib.error.URLError, OSError) as exc:
            last = str(exc)
        time.sleep(0.2)  # polling an HTTP endpoint for a state: there is no event to wait on
    raise AssertionError(f"no health line on :{port} within {HEALTH_WAIT_S} s: {last}")


@contextlib.contextmanager
def _started(roles: list[list[str]], config: Path, bin_dir: Path | None = None) -> Iterator[dict[str, int]]:
    """Each role of `roles` from `bin_dir`'s dynqos (the test's own without it), with a metrics port;
    every process stopped by its pid after."""
    procs: list[DynqosProcess] = []
    ports: dict[str, int] = {}
    executable = bin_dir / "dynqos" if bin_dir else DYNQOS
    try:
        for args in roles:
            port = free_tcp_port()
            procs.append(DynqosProcess([*args, "--metrics-port", str(port)], config, executable=executable))
            ports[" ".join(args)] = port
        yield ports
    finally:
        errors = [proc.stop() for proc in reversed(procs)]
        assert all("Traceback" not in err for err in errors), "\n".join(errors)[-3000:]


def _users_task(folder: Path) -> Path:
    """The example task of docs/offload.md as a user keeps it: a file of their own, outside dynqos."""
    task = folder / "look_at.py"
    task.write_text((Path(__file__).resolve().parent.parent / "examples" / "look_at.py").read_text())
    return task


def _config(path: Path, extra: str = "") -> Path:
    path.write_text(
        f"[zenoh]\n{flow_ports_toml()}"
        "[mpc]\nhealth_interval_s = 0.5\n[planner]\nhealth_interval_s = 0.5\n"
        "[detector]\nhealth_interval_s = 0.5\n[onboard]\nhealth_interval_s = 0.5\n" + extra
    )
    return path


def test_the_onboard_extra_runs_the_drone_without_matplotlib_scipy_or_osqp(
    wheel: Path, tmp_path: Path
) -> None:
    """`dynqos[onboard]` runs the daemon and the camera's queue-delay target; `dynqos[onboard,camera-rate]`
    also GCC (docs/camera.md), which the drone's install alone refuses in one line."""
    bin_dir = _venv_with(wheel, "onboard", tmp_path)
    python = bin_dir / "python"
    assert _absent(python, ("matplotlib", "scipy", "osqp", "aiohttp", "jsonschema")) == "[]"
    # a serial link to the flight controller (mavlink_url = "/dev/ttyACM0,921600") opens through pyserial
    serial = _run(python, "-c", "import serial; print(serial.__version__)", timeout=60)
    assert serial.returncode == 0, serial.stderr
    dynqos = bin_dir / "dynqos"
    helped = _run(dynqos, "onboard", "--help", timeout=60)
    assert helped.returncode == 0, helped.stderr
    assert "--takeoff" in helped.stdout
    # An edge service on a drone's install says which extra it needs, in one line, before any network.
    edge = _run(dynqos, "edge", "mpc", "--set", "zenoh.connect_timeout_s=0.5", timeout=60)
    assert edge.returncode == 2
    assert edge.stderr.strip() == (
        "dynqos: error: 'edge' needs osqp, which comes with the edge extra: pip install 'dynqos[edge]'"
    )
    # The daemon from the drone's install, against a router and a simulated vehicle from the test's own.
    config = _config(tmp_path / "onboard.toml")
    with _started([["edge", "router"]], config) as edge_ports:
        vehicle = DynqosProcess(["sim", "vehicle"], config)
        try:
            tasks = ["--set", f'onboard.tasks=["{_users_task(tmp_path)}:ONBOARD"]']  # a user's task too
            with _started([["onboard", *tasks]], config, bin_dir) as ports:
                line = _healthy_line(ports[" ".join(["onboard", *tasks])], time.monotonic() + HEALTH_WAIT_S)
                assert "onboard" in line, line
                assert "task_look-at=edge:0/0" in line, line  # loaded; it calls once flying offboard
                assert "camera_rate=" not in line  # no rate controller unless asked for
            assert _healthy_line(edge_ports["edge router"], time.monotonic() + HEALTH_WAIT_S)
            # The camera's delay-based rate controller needs the camera-rate extra: one line without it...
            delay = ["--set", "onboard.camera_rate_control=delay"]
            refused = _run(dynqos, "onboard", *delay, "--config", config, timeout=60)
            assert refused.returncode == 2, refused.stderr
            assert refused.stderr.count("\n") == 1, refused.stderr
            assert 'pip install "dynqos[camera-rate]"' in refused.stderr
            # ...while the queue-delay target runs on the drone's install alone (onboard/queue_rate.py)
            queue = [*delay, "--set", "onboard.camera_rate_controller=queue"]
            with _started([["onboard", *queue]], config, bin_dir) as ports:
                line = _healthy_line(ports[" ".join(["onboard", *queue])], time.monotonic() + HEALTH_WAIT_S)
                assert "camera_rate=" in line, line
            # ...and with it added to the drone's install, the daemon runs GCC.
            _install(python, f"{wheel}[onboard,camera-rate]")
            assert _absent(python, ("matplotlib", "scipy", "osqp")) == "[]"
            with _started([["onboard", *delay]], config, bin_dir) as ports:
                line = _healthy_line(ports[" ".join(["onboard", *delay])], time.monotonic() + HEALTH_WAIT_S)
                assert "camera_rate=" in line, line
                assert "camera_acks_refused=0" in line, line
        finally:
            vehicle.stop()


def test_the_realsense_extra_brings_librealsense_to_the_onboard_daemon(wheel: Path, tmp_path: Path) -> None:
    """`dynqos[realsense]`: the drone's install plus pyrealsense2, which loads (libusb-1.0 from the
    system) and, on a machine without a camera, says so in one line through the daemon's own source."""
    bin_dir = _venv_with(wheel, "realsense", tmp_path)
    probe = (
        "from dynqos.common.errors import ConfigError\n"
        "from dynqos.onboard.realsense import RealSenseCamera\n"
        "try:\n    RealSenseCamera('', 640, 480, 15)\nexcept ConfigError as exc:\n    print(exc)\n"
    )
    opened = _run(bin_dir / "python", "-c", probe, timeout=120)
    assert opened.returncode == 0, opened.stderr[-2000:]
    assert "no RealSense device is connected" in opened.stdout
    assert _absent(bin_dir / "python", ("osqp", "matplotlib")) == "[]"


def test_the_edge_extra_starts_every_edge_service_the_qos_agent_with_camara_included(
    wheel: Path, tmp_path: Path
) -> None:
    bin_dir = _venv_with(wheel, "edge", tmp_path)
    assert _absent(bin_dir / "python", ("matplotlib", "jsonschema")) == "[]"
    operator = free_tcp_port()  # nothing listens: the agent needs the API only once a drone asks
    config = _config(
        tmp_path / "edge.toml",
        f'[qos]\nbackend = "camara"\nhealth_interval_s = 0.5\n'
        f'[qos.camara]\napi_root = "http://127.0.0.1:{operator}/quality-on-demand/v1"\n'
        '[fleet_plan]\nhealth_interval_s = 0.5\ndrones = ["uav1"]\n[[fleet_plan.tasks]]\nid = "a"\n'
        "points_m = [[1.0, 1.0]]\n",
    )
    services = ("router", "mpc", "planner", "fleet-planner", "detector", "qos")
    task = _users_task(tmp_path)  # a user's own task, served as every built-in service is
    roles = [*(["edge", name] for name in services), ["edge", "serve", f"{task}:EDGE"]]
    with _started(roles, config, bin_dir) as ports:
        deadline = time.monotonic() + HEALTH_WAIT_S
        lines = {role: _healthy_line(port, deadline) for role, port in ports.items()}
    assert lines["edge qos"].startswith("qos: drones=0 sessions=0"), lines
    assert lines["edge fleet-planner"].startswith("fleet-planner: waiting drones=0/1"), lines
    assert lines[f"edge serve {task}:EDGE"].startswith("task-look-at: requests=0"), lines
    assert set(lines) == {" ".join(r) for r in roles}
    # the ROS 2 face needs the ros2 extra, and says so in one line before any network
    ros2 = _run(bin_dir / "dynqos", "edge", "ros2", "--set", "zenoh.connect_timeout_s=0.5", timeout=60)
    assert ros2.returncode == 2
    assert ros2.stderr.strip() == (
        "dynqos: error: 'edge' needs rosbags, which comes with the ros2 extra: pip install 'dynqos[ros2]'"
    )


def test_the_ros2_extra_starts_the_ros2_face_without_the_solver(wheel: Path, tmp_path: Path) -> None:
    bin_dir = _venv_with(wheel, "ros2", tmp_path)
    assert _absent(bin_dir / "python", ("osqp", "matplotlib", "zenoh_ros2_sdk")) == "[]"
    config = _config(tmp_path / "ros2.toml", "[ros2]\nhealth_interval_s = 0.5\n")
    with _started([["edge", "router"]], config), _started([["edge", "ros2"]], config, bin_dir) as ports:
        line = _healthy_line(ports["edge ros2"], time.monotonic() + HEALTH_WAIT_S)
    assert line.startswith("ros2: topics=0 published=0"), line
