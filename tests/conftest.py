"""Shared test settings: Hypothesis profiles and small helpers."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

from dynqos.common.config import ZenohConfig
from dynqos.experiment.processes import FlowPorts, free_port
from dynqos.experiment.processes import flow_ports as _flow_ports
from tests.procs import DynqosProcess

settings.register_profile("default", max_examples=200, deadline=None)
settings.register_profile(
    "ci", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "default"))

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SHARED_PX4 = Path(__file__).resolve().parents[2] / "shared" / "px4"  # a PX4 SITL build (docs/px4.md)


def flow_ports() -> FlowPorts:
    """Two distinct free TCP ports for the router's flows: ZenohConfig(**flow_ports())."""
    return _flow_ports()


def flow_ports_toml() -> str:
    """The `[zenoh]` table's two flow ports, distinct and free, as TOML lines."""
    ports = _flow_ports()
    return f"default_port = {ports['default_port']}\npriority_port = {ports['priority_port']}\n"


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now (the kernel picks it)."""
    return free_port(socket.SOCK_STREAM)


@pytest.fixture
def edge(tmp_path: Path) -> Iterator[tuple[Path, ZenohConfig, list[DynqosProcess]]]:
    """A router on free ports and its config file (with short health intervals), and a list for the
    test's own processes, stopped at the end in reverse order."""
    zcfg = ZenohConfig(**flow_ports())
    config = tmp_path / "edge.toml"
    config.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        "[mpc]\nhealth_interval_s = 1\n[planner]\nlead_in_s = 1\nhealth_interval_s = 1\n"
    )
    procs: list[DynqosProcess] = []
    try:
        procs.append(DynqosProcess(["edge", "router"], config))
        yield config, zcfg, procs
    finally:
        for proc in reversed(procs):
            proc.stop()


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture
def px4_dir() -> Path:
    """PX4's folder for the tests that fly PX4 itself; they skip, saying why, where it is absent."""
    if not (SHARED_PX4 / "bin" / "px4").is_file():
        pytest.skip(f"no PX4 SITL build at {SHARED_PX4} (docs/px4.md says how to make one)")
    return SHARED_PX4


@pytest.fixture
def librealsense() -> None:
    """Skip, saying why, where librealsense cannot load (it needs libusb-1.0 from the system); under
    CI, which installs it (.ci/run), fail loudly instead."""
    try:
        import pyrealsense2  # noqa: F401
    except ImportError as exc:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"librealsense cannot load here ({exc}): apt install libusb-1.0-0")


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """CI's slow pass flies a failed flight once more (`--reruns 1`, .ci/run): the first flight's
    failure is printed here, so a pass on the second flight never hides what broke the first."""
    if report.outcome == "rerun":
        lines = report.longreprtext.splitlines()
        took = f"{report.duration:.0f} s"
        print(f"\nRERUN {report.nodeid}: its first try failed ({took}); the end of its report:")
        print("\n".join(f"    {line}" for line in lines[-25:]))
