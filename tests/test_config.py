from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dynqos.cli import main
from dynqos.common.config import Config, load_config, to_toml
from dynqos.common.errors import ConfigError


def write(tmp_path: Path, text: str, name: str = "dynqos.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_defaults_are_the_papers() -> None:
    config = load_config()
    sup = config.supervisor
    assert sup.mu == (3.0, 5.0, 5.0)
    assert sup.rho == (61.0, 27.0, 3.0)
    assert sup.w == (0.35, 0.65)
    assert sup.window == (10, 50)
    assert (sup.risk_high_m, sup.risk_medium_m) == (3.0, 5.0)
    assert sup.watchdog_s == pytest.approx(3 * config.control.t_mpc_s)
    assert config.control.t_mpc_s == 0.05
    assert (config.zenoh.default_port, config.zenoh.priority_port) == (7447, 7448)


def test_a_file_sets_only_what_it_changes(tmp_path: Path) -> None:
    config = load_config(
        write(tmp_path, "[supervisor]\nth_lat = 0.7\nmu = [1, 2, 3]\n[drone]\nid = 'hex-2'\n")
    )
    assert config.supervisor.th_lat == 0.7
    assert config.supervisor.mu == (1.0, 2.0, 3.0)
    assert config.drone.id == "hex-2"
    assert config.supervisor.rho == Config().supervisor.rho


def test_overrides_apply_after_the_file(tmp_path: Path) -> None:
    path = write(tmp_path, "[supervisor]\nth_lat = 0.7\n")
    config = load_config(path, ["supervisor.th_lat=0.9", "drone.id=uav7", "supervisor.mode='stochastic'"])
    assert config.supervisor.th_lat == 0.9
    assert config.drone.id == "uav7"
    assert config.supervisor.mode == "stochastic"


def test_effective_config_round_trips_through_toml(tmp_path: Path) -> None:
    config = load_config(None, ["zenoh.edge_host=edge.local", "supervisor.seed=3"])
    assert load_config(write(tmp_path, to_toml(config))) == config


@pytest.mark.parametrize(
    ("text", "key", "reason"),
    [
        ("[supervisor]\nbogus = 1\n", "supervisor.bogus", "unknown key"),
        ("[nope]\nx = 1\n", "nope", "unknown key"),
        ("[supervisor]\nth_lat = 'high'\n", "supervisor.th_lat", "expected a number"),
        ("[supervisor]\nth_lat = 1.5\n", "supervisor.th_lat", "must be in (0, 1)"),
        ("[supervisor]\nth_lat = nan\n", "supervisor.th_lat", "finite"),
        ("[supervisor]\nw = [0.5, 0.6]\n", "supervisor.w", "sum to 1"),
        ("[supervisor]\nmu = [1, 2]\n", "supervisor.mu", "array of 3"),
        ("[supervisor]\nmu = 3\n", "supervisor.mu", "expected an array"),
        ("[supervisor]\nwindow = [10, 2.5]\n", "supervisor.window[1]", "expected an integer"),
        ("[supervisor]\nmode = 'random'\n", "supervisor.mode", "not one of"),
        ("[zenoh]\nshared_memory = 1\n", "zenoh.shared_memory", "true or false"),
        ("[drone]\nid = 'has space'\n", "drone.id", "1 to 32 characters"),
        ("[drone]\nid = 5\n", "drone.id", "expected a string"),
        ("drone = 5\n", "drone", "expected a table"),
        ("[zenoh]\ndefault_port = 70000\n", "zenoh.default_port", "TCP port"),
        ("[zenoh]\npriority_port = 7447\n", "zenoh.priority_port", "differ"),
        ("[zenoh]\nmax_links = 1\n", "zenoh.max_links", "two flows"),
        ("[control]\nhorizon = 2\n", "control.horizon", "5..200"),
        ("[supervisor]\ncc_fast_window = 60\n", "supervisor.cc_fast_window", "0..window[1]"),
        ("[supervisor]\nprobe_s = -1\n", "supervisor.probe_s", "0..600 s"),
        ("[onboard]\ncamera_pace_mbps = -5\n", "onboard.camera_pace_mbps", "0: no pacing"),
        ("[onboard]\ncamera_part_bytes = 100\n", "onboard.camera_part_bytes", "512..1048576"),
        ("[vehicle]\ngust_tau_s = 0\n", "vehicle.gust_tau_s", "0.05..600 s"),
        ("[zenoh]\nacl_ros2_clients = ['ros-ground']\n", "zenoh.acl_ros2_clients", "access control"),
        ("[zenoh]\nacl_ros2_prefix = '9lives'\n", "zenoh.acl_ros2_prefix", "must be a ROS name"),
        ("[qos.camara]\nprofile_recheck_s = 0\n", "qos.camara.profile_recheck_s", "1..86400 s"),
        (
            "[qos.camara]\napplication_server_addresses = ['10.0.0.1']\n",
            "qos.camara.application_server_addresses",
            'needs api_version = "1.2.0"',
        ),
        (
            "[qos.camara]\napi_version = '1.2.0'\napplication_server_addresses = ['10.0.0.0/24']\n",
            "qos.camara.application_server_addresses",
            "not a single IP address",
        ),
        (
            "[qos.camara]\napi_version = '1.2.0'\napplication_server_addresses = ['10.0.0.1', '10.0.0.1']\n",
            "qos.camara.application_server_addresses",
            "16 different",
        ),
        ("[qos.camara]\napi_version = '1.3.0'\n", "qos.camara.api_version", "not one of"),
        ("[cell]\nqod_api_version = '2'\n", "cell.qod_api_version", "not one of"),
        (
            "[[cell.events]]\nat_s = 1\nkind = 'qod_profile'\nstatus = 'INACTIVE'\n",
            "cell.events[0].profile",
            "names its profile",
        ),
        ("[qos]\npolicy = 'arbiter'\n", "qos.policy", 'needs backend = "camara"'),
        ("[qos]\npolicy = 'fair'\n", "qos.policy", "not one of"),
        ("[qos.arbiter]\nmax_share = 0.5\n", "qos.arbiter.uplink_mbps", "required"),
        ("[qos.arbiter]\nmax_grants = -2\n", "qos.arbiter.max_grants", "-1 (no limit)"),
        ("[qos.arbiter]\nmin_hold_s = 10\nrotate_after_s = 5\n", "qos.arbiter.rotate_after_s", "min_hold_s"),
        # tokens and device identities cross these URLs: plain http only to this host
        (
            "[qos.camara]\napi_root = 'http://api.operator.example/qod/v1'\n",
            "qos.camara.api_root",
            "https://",
        ),
        (
            "[qos.camara]\ntoken_url = 'http://10.0.0.1/token'\nclient_id = 'x'\nclient_secret_file = 'f'\n",
            "qos.camara.token_url",
            "https://",
        ),
        ("[qos.camara]\nsink = 'http://127.0.0.1.example/qod'\n", "qos.camara.sink", "https://"),
        ("[qos.camara]\nprofiles_root = 'ftp://x/y'\n", "qos.camara.profiles_root", "http(s) URL"),
        (
            "[qos.camara]\nheaders_file = 'h'\ntoken_url = 'https://a.example/t'\nclient_id = 'x'\n"
            "client_secret_file = 'f'\n",
            "qos.camara.headers_file",
            "instead of token_url",
        ),
    ],
)
def test_bad_values_name_file_key_and_reason(tmp_path: Path, text: str, key: str, reason: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.key == key
    assert reason in info.value.reason
    assert str(info.value).startswith(f"{path}: {key}: ")


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(write(tmp_path, "[supervisor\n"))
    (tmp_path / "dir.toml").mkdir()
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "dir.toml")


def test_bad_overrides() -> None:
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        load_config(None, ["supervisor.th_lat"])
    with pytest.raises(ConfigError, match="empty key"):
        load_config(None, ["supervisor..th_lat=1"])
    with pytest.raises(ConfigError, match="not a table"):
        load_config(None, ["drone.id=x", "drone.id.more=1"])


def test_cli_config_show_prints_the_effective_config(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    path = write(tmp_path, "[supervisor]\nth_lat = 0.65\n")
    assert main(["config", "show", str(path), "--set", "drone.id=uav9"]) == 0
    out = capsys.readouterr().out
    assert "th_lat = 0.65" in out
    assert 'id = "uav9"' in out
    assert main(["config", "show", "--config", str(path)]) == 0


def test_cli_rejects_two_different_config_files(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["config", "show", "a.toml", "--config", "b.toml"]) == 2
    assert "two config files" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["config", "show", "missing.toml"], "missing.toml: config file not found"),
        (["config", "show", "--set", "supervisor.th_lat=2"], "supervisor.th_lat: must be in (0, 1)"),
        (["config", "show", "--set", "zenoh.nope=1"], "zenoh.nope: unknown key"),
    ],
)
def test_console_script_errors_are_one_line_and_exit_2(args: list[str], message: str) -> None:
    exe = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")
    result = subprocess.run([exe, *args], capture_output=True, text=True, timeout=60, check=False)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("dynqos: error: ")
    assert message in lines[0]
    assert "Traceback" not in result.stderr


def test_console_script_help_and_version() -> None:
    exe = shutil.which("dynqos") or str(Path(sys.executable).parent / "dynqos")
    result = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60, check=True)
    assert "config" in result.stdout
    version = subprocess.run([exe, "version"], capture_output=True, text=True, timeout=60, check=True)
    assert version.stdout.startswith("dynqos ")


def test_per_drone_missions_and_the_arbiter_round_trip_and_reach_the_planner(tmp_path: Path) -> None:
    from dynqos.edge.planner.service import mission_from_config

    path = write(
        tmp_path,
        "[planner]\naltitude_m = 2.0\n[planner.drones.uav2]\ncenter_m = [10.0, -4.0]\nradius_m = 1.5\n"
        "[planner.drones.uav3]\nmission = 'hover'\ncenter_m = [-6.0, 0.0]\n"
        "[qos]\nbackend = 'camara'\npolicy = 'arbiter'\n[qos.camara]\napi_root = 'http://127.0.0.1:1'\n"
        "[qos.arbiter]\nmax_grants = 2\n",
    )
    config = load_config(path)
    again = write(tmp_path, to_toml(config), "again.toml")
    assert load_config(again) == config
    assert mission_from_config(config.planner, "uav1").center_m == (0.0, 0.0)  # not listed: the planner's
    assert mission_from_config(config.planner, "uav1").altitude_m == 2.0
    uav2 = mission_from_config(config.planner, "uav2")
    assert (uav2.kind, uav2.center_m, uav2.radius_m, uav2.altitude_m) == ("circle", (10.0, -4.0), 1.5, 1.5)
    assert mission_from_config(config.planner, "uav3").kind == "hover"
    assert config.qos.arbiter.max_grants == 2


def test_a_headers_file_is_name_value_lines_and_a_bad_one_names_its_line_not_its_value(
    tmp_path: Path,
) -> None:
    from dynqos.common.camara import read_headers

    good = tmp_path / "good"
    good.write_text("# keys\n\nX-API-Key:  s3cret value \nX-Other: 1\n")
    assert read_headers(str(good)) == {"X-API-Key": "s3cret value", "X-Other": "1"}
    bad = tmp_path / "bad"
    bad.write_text("X-API-Key: fine\nno colon here s3cret\n")
    with pytest.raises(ConfigError, match="line 2 is not") as info:
        read_headers(str(bad))
    assert "s3cret" not in str(info.value)
    (tmp_path / "empty").write_text("# nothing\n")
    with pytest.raises(ConfigError, match="names no header"):
        read_headers(str(tmp_path / "empty"))
    assert read_headers("") == {}


def test_every_section_checks_its_declared_ranges_however_it_is_built() -> None:
    """A range is declared once on its field (common/config/validate.py In) and holds for a section made
    in code as for one read from a file; every section is @checked, so a declared range cannot be
    silently skipped."""
    import dataclasses

    from dynqos.common import config as config_module
    from dynqos.common.config import CamaraConfig, CellConfig, ControlConfig
    from dynqos.common.config.validate import declared

    with pytest.raises(ConfigError, match=r"duration_s: must be in 1\.\.10000000 s"):
        CamaraConfig(duration_s=0)
    with pytest.raises(ConfigError, match=r"priority_weight: must be in \(0, 1000\]"):
        CellConfig(priority_weight=0.0)
    with pytest.raises(ConfigError, match="setpoint_hz"):
        ControlConfig(setpoint_hz=2.0)  # the open end
    assert ControlConfig(setpoint_hz=1000).setpoint_hz == 1000  # the closed one
    sections = [
        obj
        for obj in vars(config_module).values()
        if isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__name__.endswith("Config")
    ]
    assert len(sections) >= 15
    unchecked = [
        s.__name__ for s in sections if s.__post_init__.__qualname__ != "checked.<locals>.__post_init__"
    ]
    assert unchecked == [], "sections without @checked"
    assert sum(len(declared(s)) for s in sections) >= 90  # the ranges, declared on their fields


def test_a_scenario_sets_any_setting_by_section_over_what_it_derives(tmp_path: Path) -> None:
    """[scenario.config.<section>] carries dynqos settings as a config file writes them: they reach the
    flight's config over the scenario's own (the breeze it flies in, its camera parts), are checked
    when the scenario is read, and a key that became a setting says where it went."""
    from dynqos.common.config import ZenohConfig
    from dynqos.plan.scenario import load_scenario, scenario_config

    path = write(
        tmp_path,
        "[scenario]\nname = 'windy'\n[scenario.config.vehicle]\nwind_mps = [3.0, 1.0, 0.0]\n"
        "[scenario.config.supervisor]\nth_lat = 0.6\n[scenario.config.onboard]\ncamera_part_bytes = 2048\n",
    )
    built = scenario_config(load_scenario(path), zenoh=ZenohConfig(), fc_port=15000, gcs_port=16000)
    assert built.vehicle.wind_mps == (3.0, 1.0, 0.0)
    assert built.vehicle.gust_std_mps == 0.5  # the scenario's own, not overridden
    assert built.supervisor.th_lat == 0.6
    assert built.onboard.camera_part_bytes == 2048
    assert built.supervisor.seed == 0  # what the scenario derives itself still holds
    bad = write(tmp_path, "[scenario]\nname = 'x'\n[scenario.config.cell]\njitter_ms = -1\n", "bad.toml")
    with pytest.raises(ConfigError, match=r"scenario\.config\.cell\.jitter_ms: must be in 0\.\.10000 ms"):
        load_scenario(bad)
    unknown = write(tmp_path, "[scenario]\nname = 'x'\n[scenario.config.cel]\nx = 1\n", "unknown.toml")
    with pytest.raises(ConfigError, match=r"scenario\.config\.cel: unknown key"):
        load_scenario(unknown)
    moved = write(tmp_path, "[scenario]\nname = 'x'\ngust_std_mps = 1.0\n", "moved.toml")
    with pytest.raises(ConfigError, match=r"\[scenario\.config\.vehicle\] gust_std_mps"):
        load_scenario(moved)
