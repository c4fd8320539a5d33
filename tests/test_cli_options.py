"""Common options and the environment: a setting given anywhere is applied or refused, never ignored.

argparse copies a subcommand's defaults over what its parent parsed, so `dynqos config --set X show`
used to print the default. These run the real `main` in-process (no subprocess needed: it parses,
loads and prints) and read what it printed.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from dynqos.cli import main
from dynqos.common.config import environment_overrides, load_config
from dynqos.common.errors import ConfigError


def _show(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _drone_id(toml: str) -> str:
    lines = toml.splitlines()
    return lines[lines.index("[drone]") + 1]


@pytest.mark.parametrize(
    "argv",
    [
        ["--set", "drone.id=zz", "config", "show"],
        ["config", "--set", "drone.id=zz", "show"],
        ["config", "show", "--set", "drone.id=zz"],
    ],
    ids=["before-command", "before-action", "after-action"],
)
def test_set_works_at_every_level(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _show(capsys, *argv)
    assert code == 0
    assert _drone_id(out) == 'id = "zz"'


def test_sets_at_several_levels_all_apply_the_innermost_last(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _show(
        capsys, "--set", "drone.id=outer", "config", "--set", "supervisor.th_lat=0.7", "show",
        "--set", "drone.id=inner",
    )  # fmt: skip
    assert code == 0
    assert _drone_id(out) == 'id = "inner"'
    assert "th_lat = 0.7" in out


@pytest.mark.parametrize("level", ["before-command", "before-action", "after-action"])
def test_a_missing_config_file_fails_at_every_level(level: str, capsys: pytest.CaptureFixture[str]) -> None:
    option = ["--config", "/nonexistent/dynqos.toml"]
    argv = {
        "before-command": [*option, "config", "show"],
        "before-action": ["config", *option, "show"],
        "after-action": ["config", "show", *option],
    }[level]
    code, out, err = _show(capsys, *argv)
    assert code == 2
    assert out == ""
    assert "/nonexistent/dynqos.toml: config file not found" in err


def test_two_config_files_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--config", "a.toml", "config", "show", "--config", "b.toml"])
    assert stop.value.code == 2
    assert "two config files given (a.toml and b.toml)" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [["demo", "--set", "drone.id=zz"], ["--set", "drone.id=zz", "demo"], ["--config", "x.toml", "version"]],
)
def test_commands_that_read_no_settings_refuse_them(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "--set" in err or "--config" in err


def test_the_environment_sets_nested_settings_and_show_says_so(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("DYNQOS_DRONE__ID", "uav7")
    monkeypatch.setenv("DYNQOS_QOS__CAMARA__API_ROOT", "http://127.0.0.1:9/qod/v1")
    monkeypatch.setenv("dynqos_supervisor__th_lat", "0.65")  # case-insensitive, as pydantic-settings
    monkeypatch.setenv("DYNQOS_SOAK_S", "300")  # no `__`: not a setting, left alone
    code, out, _ = _show(capsys, "config", "show")
    assert code == 0
    assert _drone_id(out) == 'id = "uav7"'
    assert 'api_root = "http://127.0.0.1:9/qod/v1"' in out
    assert "th_lat = 0.65" in out
    assert "# from the environment: DYNQOS_DRONE__ID -> drone.id=uav7" in out
    assert "SOAK" not in out


def test_set_wins_over_the_environment_which_wins_over_the_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "c.toml"
    config.write_text('[drone]\nid = "from-file"\n[supervisor]\nth_lat = 0.55\n')
    monkeypatch.setenv("DYNQOS_DRONE__ID", "from-env")
    monkeypatch.setenv("DYNQOS_SUPERVISOR__TH_LAT", "0.6")
    code, out, _ = _show(capsys, "config", "show", str(config), "--set", "drone.id=from-set")
    assert code == 0
    assert _drone_id(out) == 'id = "from-set"'
    assert "th_lat = 0.6\n" in out


def test_a_bad_environment_setting_names_the_variable(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("DYNQOS_DRONE__IDENT", "uav7")
    code, _, err = _show(capsys, "config", "show")
    assert code == 2
    assert err.strip().count("\n") == 0
    assert "environment variable DYNQOS_DRONE__IDENT" in err
    monkeypatch.delenv("DYNQOS_DRONE__IDENT")
    monkeypatch.setenv("DYNQOS_SUPERVISOR__TH_LAT", "high")
    code, _, err = _show(capsys, "config", "show")
    assert code == 2
    assert "DYNQOS_SUPERVISOR__TH_LAT" in err


def test_environment_overrides_are_pure_and_ordered() -> None:
    env = {"DYNQOS_B__X": "1", "DYNQOS_A__Y": "two", "PATH": "/bin", "DYNQOS_SOAK_S": "3"}
    assert environment_overrides(env) == [("DYNQOS_A__Y", "a.y=two"), ("DYNQOS_B__X", "b.x=1")]
    with pytest.raises(ConfigError, match="environment variable DYNQOS_A__Y: a: unknown key"):
        load_config(environment=environment_overrides(env))


def test_the_demo_s_help_names_every_shipped_scenario(capsys: pytest.CaptureFixture[str]) -> None:
    from dynqos.cli.experiment_cmd import DEFAULT_FOUR
    from dynqos.plan.scenario import DEFAULT_SCENARIOS, builtin_names

    assert DEFAULT_FOUR == DEFAULT_SCENARIOS
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    text = " ".join(capsys.readouterr().out.split()).replace("- ", "-")  # argparse breaks names at hyphens
    for name in builtin_names():
        assert name in text, name


def test_math_threads_are_set_before_numpy_loads_and_a_users_variable_wins() -> None:
    """`[mpc] math_threads` reaches the BLAS under numpy only if set before numpy is imported: run_edge
    sets it before it imports the service, and nothing before it imports numpy."""
    import subprocess
    import sys

    from dynqos.cli.edge_cmd import MATH_THREADS_VARIABLES, limit_math_threads

    environ = {"OMP_NUM_THREADS": "4"}
    limit_math_threads(1, environ)
    assert environ == {**dict.fromkeys(MATH_THREADS_VARIABLES, "1"), "OMP_NUM_THREADS": "4"}
    probe = (
        "import sys; from dynqos.cli import main; from dynqos.common.config import load_config; "
        "load_config(None, ['mpc.math_threads=3']); print('numpy' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    with pytest.raises(ConfigError, match="math_threads"):
        load_config(None, ["mpc.math_threads=0"])
