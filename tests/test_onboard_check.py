"""`dynqos onboard check`, the preflight, against the demo's own processes (a router and the simulated
vehicle, signing on) and the real RGB-D frames as the camera: it passes; then each part missing or
wrong in turn, and the line that fails names it (docs/onboard.md, "Preflight")."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from dynqos.common import mavsign
from dynqos.onboard.check import check_unit
from tests.conftest import flow_ports_toml
from tests.procs import DYNQOS, DynqosProcess
from tests.test_vehicle_mavlink import free_udp_port

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


def _check(config: Path, *settings: str, measure_s: float = 2.0) -> tuple[int, dict[str, str]]:
    """Exit code and each item's line (by name) of `dynqos onboard check`."""
    args = [DYNQOS, "onboard", "check", "--config", str(config), "--measure-s", str(measure_s)]
    for setting in settings:
        args += ["--set", setting]
    done = subprocess.run(args, capture_output=True, text=True, timeout=90)
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    lines = [line for line in done.stdout.splitlines() if line.startswith(("PASS", "FAIL"))]
    return done.returncode, {line[6:29].strip(): line for line in lines}


def test_the_preflight_passes_against_the_demo_and_names_each_missing_part(
    shared_data: Path, tmp_path: Path
) -> None:
    key = mavsign.write_key(tmp_path / "fc.key")
    api = free_udp_port()
    config = tmp_path / "drone.toml"
    config.write_text(
        f"[zenoh]\n{flow_ports_toml()}"
        "connect_timeout_s = 1\n"
        f"[vehicle]\noffboard_bind_port = 0\ngcs_bind_port = 0\noffboard_remote_port = {api}\n"
        f'gcs_remote_port = {free_udp_port()}\nsigning_key = "{key}"\n'
        f'[onboard]\nmavlink_url = "udpin:127.0.0.1:{api}"\nmavlink_signing_key = "{key}"\n'
        f'camera = "files"\nfiles_dir = "{shared_data / "rgbd"}"\ncamera_fps = 10\nfc_timeout_s = 5\n'
    )
    color_only = tmp_path / "color-only"
    color_only.mkdir()
    (color_only / "color_1.png").write_bytes((shared_data / "rgbd" / "color_1.png").read_bytes())
    router = DynqosProcess(["edge", "router"], config)
    vehicle = DynqosProcess(["sim", "vehicle", "--duration", "170"], config)
    try:
        code, items = _check(config)
        assert code == 0, items
        assert set(items) == {"flight controller", "MAVLink signing", "camera", "router, default flow",
                              "router, priority flow", "clock offset to edge", "QoS",
                              "systemd unit"}  # fmt: skip
        assert all(line.startswith("PASS") for line in items.values()), items
        assert "position 50 Hz, attitude 50 Hz" in items["flight controller"]
        assert "0 refused" in items["MAVLink signing"]
        assert "valid depth" in items["camera"]
        assert "ms to the router's clock" in items["clock offset to edge"]

        ports = dict(line.split(" = ") for line in config.read_text().splitlines() if "_port = " in line)
        up, prio = (f'"127.0.0.1:{ports[k]}"' for k in ("default_port", "priority_port"))
        two_paths = (  # path b dials a port nobody listens on: its line says so, path a's passes
            f'onboard.paths=[{{name="a", connect_default={up}, connect_priority={prio}}},'
            f'{{name="b", connect_default="127.0.0.1:{free_udp_port()}", connect_priority={prio}}}]'
        )
        # what follows looks only at which lines pass: rates counted over half a second
        code, items = _check(config, two_paths, measure_s=0.5)
        assert code == 1
        assert items["router a, default flow"].startswith("PASS"), items
        assert items["router b, default flow"].startswith("FAIL"), items
        assert items["router b, priority flow"].startswith("PASS"), items

        other_key = mavsign.write_key(tmp_path / "other.key")  # the FC (50 Hz) goes unheard for 1 s
        code, items = _check(
            config, "onboard.fc_timeout_s=1", f'onboard.mavlink_signing_key="{other_key}"', measure_s=0.5
        )
        assert code == 1
        assert items["flight controller"].startswith("FAIL")  # nothing it accepts: the FC is not heard
        assert items["MAVLink signing"].startswith("FAIL")
        assert "refused" in items["MAVLink signing"]

        code, items = _check(config, f'onboard.files_dir="{color_only}"', measure_s=0.5)
        assert code == 1
        assert items["camera"].startswith("FAIL")
        assert "no depth" in items["camera"]
        assert items["flight controller"].startswith("PASS")
    finally:
        vehicle.stop()
        router.stop()
    code, items = _check(
        config, "onboard.fc_timeout_s=1", measure_s=0.5
    )  # neither the vehicle nor the router is up
    assert code == 1
    failed = {name for name, line in items.items() if line.startswith("FAIL")}
    assert failed == {"flight controller", "router, default flow", "router, priority flow",
                      "clock offset to edge"}, items  # fmt: skip
    assert "nothing accepts a connection there" in items["router, default flow"]


def test_the_systemd_item_says_when_systemd_does_not_run(tmp_path: Path) -> None:
    item = check_unit(tmp_path / "absent")
    assert item.ok
    assert "systemd is not running here" in item.detail


def test_each_offloaded_task_is_an_item_its_module_loaded_or_said_why_not(tmp_path: Path) -> None:
    from dataclasses import replace

    from dynqos.common.config import Config
    from dynqos.onboard.check import check_tasks

    example = Path(__file__).resolve().parents[1] / "examples" / "look_at.py"
    (tmp_path / "broken.py").write_text("raise RuntimeError('no GPU here')\n")
    config = Config()
    config = replace(
        config,
        onboard=replace(config.onboard, tasks=(f"{example}:ONBOARD", f"{tmp_path / 'broken.py'}:ONBOARD")),
    )
    good, bad = check_tasks(config)
    assert good.ok
    assert good.line().startswith("PASS  task look-at")
    assert "10 Hz, deadline 80 ms, control flow" in good.detail
    assert not bad.ok
    assert "RuntimeError: no GPU here" in bad.detail
    assert check_tasks(Config()) == []  # no item where no task runs
