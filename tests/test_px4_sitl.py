"""PX4 SITL as dynqos starts it (sim/vehicle/px4_sitl.py): the folder checked with one line, the
parameters dynqos boots it with, its own bin/ of links, and a real PX4 booted, heard where the onboard
daemon listens and stopped cleanly by its pid, its ULog kept (skipped where no PX4 build is at hand)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from dynqos.common.config import Px4Config
from dynqos.common.errors import ConfigError, DynqosError
from dynqos.common.geo import Geo
from dynqos.onboard.fclink import FcLink
from dynqos.sim.vehicle.px4_origin import DEFAULT_HOME, ORIGIN_TOLERANCE_M, Home
from dynqos.sim.vehicle.px4_sitl import (
    DYNQOS_PARAMETERS,
    Px4Ports,
    boot_environment,
    free_instances,
    private_bin,
    px4_folder,
    ulogs,
)
from tests.procs import DynqosProcess

DYNQOS = [sys.executable, "-m", "dynqos.cli"]


def test_a_missing_or_wrong_px4_folder_is_one_line_saying_what_to_set(tmp_path: Path) -> None:
    with pytest.raises(DynqosError, match=r"set \[px4\] dir \(or DYNQOS_PX4__DIR, or --px4-dir\)"):
        px4_folder("")
    with pytest.raises(DynqosError, match="no executable bin/px4"):
        px4_folder(str(tmp_path))
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "px4").write_text("#!/bin/sh\n")
    (tmp_path / "bin" / "px4").chmod(0o755)
    with pytest.raises(DynqosError, match=r"no etc/init\.d-posix/rcS"):
        px4_folder(str(tmp_path))


def test_demo_with_px4_and_no_folder_ends_with_one_line_and_no_traceback() -> None:
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("DYNQOS_PX4__")}
    done = subprocess.run(
        [*DYNQOS, "demo", "--vehicle", "px4", "--scenario", "baseline"],
        capture_output=True, text=True, env=env, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("dynqos: error: no PX4 folder")


def test_px4_boots_with_dynqos_parameters_under_the_users_own() -> None:
    env = boot_environment(
        Px4Config(params={"COM_OBL_RC_ACT": 5}, ulog=False), 0, {"PX4_PARAM_X": "1", "PATH": "/bin"}
    )
    assert env["PX4_PARAM_COM_OBL_RC_ACT"] == "5"  # the user's, over dynqos's Land
    assert env["PX4_PARAM_COM_RCL_EXCEPT"] == "4"
    assert env["PX4_PARAM_SDLOG_BACKEND"] == "0"  # no ULog asked for: PX4's logger does not start
    assert "PX4_PARAM_X" not in env  # none left over from the caller's environment
    assert env["PX4_SIM_MODEL"] == "sihsim_quadx"
    assert {f"PX4_PARAM_{n}" for n in DYNQOS_PARAMETERS} <= set(env)
    with pytest.raises(ConfigError, match="not a PX4 parameter name"):
        Px4Config(params={"com_obl": 1})


def test_a_start_in_metres_is_a_home_that_far_from_the_common_origin() -> None:
    origin = Home.of({})
    assert (origin.lat_deg, origin.lon_deg) == DEFAULT_HOME[:2]
    moved = origin.shifted((30.0, -20.0))
    north, east = Geo(origin.lat_deg, origin.lon_deg).to_local(moved.lat_deg, moved.lon_deg)
    assert (round(north, 6), round(east, 6)) == (30.0, -20.0)
    assert moved.environment()["PX4_HOME_ALT"] == "489.400"
    with pytest.raises(DynqosError, match="must be numbers"):
        Home.of({"PX4_HOME_LAT": "north"})


def test_each_instance_has_its_own_bin_of_links_to_the_one_binary(tmp_path: Path) -> None:
    """A copy whose px4-<module> links became plain files (as a copy without links makes them) boots."""
    folder = tmp_path / "px4"
    (folder / "bin").mkdir(parents=True)
    (folder / "bin" / "px4").write_text("binary")
    (folder / "bin" / "px4-param").write_text("px4")  # a link that lost itself
    (folder / "bin" / "px4-alias.sh").write_text("alias")
    program = private_bin(folder, tmp_path / "i0")
    assert program.resolve() == (folder / "bin" / "px4").resolve()
    assert (tmp_path / "i0" / "bin" / "px4-param").resolve() == (folder / "bin" / "px4").resolve()
    assert (tmp_path / "i0" / "bin" / "px4-alias.sh").read_text() == "alias"
    assert private_bin(folder, tmp_path / "i0") == program  # again: the links are made anew


@pytest.mark.integration
@pytest.mark.timeout(90)
def test_a_real_px4_boots_is_heard_where_the_daemon_listens_and_stops_cleanly(
    px4_dir: Path, tmp_path: Path
) -> None:
    instance = free_instances(1)[0]
    ports = Px4Ports(instance)
    config = tmp_path / "dynqos.toml"
    config.write_text(f'[px4]\ndir = "{px4_dir}"\n')
    workdir = tmp_path / "px4"
    args = ["sim", "px4", "--instance", str(instance), "--workdir", str(workdir), "--start", "3,-2"]
    px4 = DynqosProcess(args, config, 60)
    link = FcLink(f"udpin:127.0.0.1:{ports.offboard_remote}", fc_system_id=ports.system_id)
    try:
        assert px4.info["system_id"] == ports.system_id
        assert isinstance(px4.info["px4_pid"], int)
        link.start()  # where PX4 sends its offboard link, as the onboard daemon listens
        assert link.wait_ready(20), "no heartbeat and position from PX4 on its offboard link"
        assert link.state is not None
        # It stands where it was told, in the fleet's frame (SIH's home is a float32: ~0.4 m steps)
        assert math.dist(link.state.pos_m[:2], (3.0, -2.0)) < ORIGIN_TOLERANCE_M
        assert link.set_param("MIS_TAKEOFF_ALT", 1.5) == 0  # PX4 echoes the take-off altitude
        assert not link.armed
    finally:
        link.close()
        err = px4.stop()  # SIGTERM to our child, which stops PX4 by its pid
    assert px4.proc.returncode == 0, err[-2000:]
    assert "stopped (exit 0)" in err
    assert ulogs(workdir), "PX4 wrote no ULog"
    assert not Path(f"/proc/{px4.info['px4_pid']}").exists(), "PX4 outlived its wrapper"
