"""The whole loop under the production security: mutual TLS, one identity per process and the router's
least-privilege access control. Each service shows its own certificate; the drone flies offloaded,
its camera reaches the detector, the detections, the MPC's commands and the QoS agent's grant come back.
A policy that forgot a key one of them needs would break one of these paths (docs/security.md).
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from dynqos.common.certs import make_dev_pki
from dynqos.common.config import ZenohConfig
from tests.conftest import flow_ports
from tests.procs import DynqosProcess
from tests.test_onboard_loop import loop_config

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]


def _tls(pki: Path, name: str) -> list[str]:
    settings = [
        "zenoh.tls=true",
        f'zenoh.tls_ca="{pki}/ca.pem"',
        f'zenoh.tls_cert="{pki}/{name}.pem"',
        f'zenoh.tls_key="{pki}/{name}-key.pem"',
    ]
    return [arg for s in settings for arg in ("--set", s)]


def test_the_loop_closes_with_each_process_on_its_own_identity(tmp_path: Path) -> None:
    pki = tmp_path / "pki"
    make_dev_pki(pki, ["uav1"], [])
    zcfg = ZenohConfig(**flow_ports())
    config = loop_config(tmp_path, zcfg)
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router"] = DynqosProcess(
            ["edge", "router", *_tls(pki, "router"), "--set", 'zenoh.acl_drones=["uav1"]'], config
        )
        procs["vehicle"] = DynqosProcess(["sim", "vehicle", "--duration", "600"], config)
        for service in ("planner", "mpc", "detector", "qos"):
            procs[service] = DynqosProcess(["edge", service, *_tls(pki, f"edge-{service}")], config)
        procs["onboard"] = DynqosProcess(
            ["onboard", "--takeoff", *_tls(pki, "uav1")],
            config,  # qos dynamic: it asks the agent
        )
        onboard = procs["onboard"]
        assert onboard.proc.stderr is not None
        edge_control = frames = detections = commands = 0
        grant_heard = False
        deadline = time.monotonic() + 120
        for line in onboard.lines(
            timeout_s=30
        ):  # the daemon's log (a health line a second) until the loop is proven
            assert time.monotonic() < deadline, "the loop did not close within 120 s"
            grant_heard = grant_heard or "qos: the network's grant is" in line
            if "onboard health:" in line:
                fields = dict(re.findall(r"(\w+)=(\S+)", line))
                commands, frames = int(fields["commands_ok"]), int(fields["frames"])
                detections, edge_control = int(fields["detections"]), int(fields["edge_ticks"])
            if commands > 100 and frames > 10 and detections > 10 and edge_control > 100 and grant_heard:
                break
        print(f"commands {commands}, frames {frames}, detections {detections}, edge ticks {edge_control}")
        assert commands > 100  # the MPC read the state and the planner's reference; its commands came back
        assert detections > 10  # the detector read the camera; its detections came back
        assert grant_heard  # the QoS agent read the request; its grant came back
    finally:
        logs = {name: procs[name].stop() for name in reversed(list(procs))}
    assert "uav1 asks for the first time" in logs["qos"]
    assert "TLS WITHOUT ACCESS CONTROL" not in logs["router"]
