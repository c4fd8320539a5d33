"""Every `dynqos` command, fed a missing file, a bad value, an unknown key or an endpoint it cannot
reach, ends with one clear line on stderr and exit code 2: never a traceback."""

from __future__ import annotations

import concurrent.futures
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from dynqos.cli import main
from tests.procs import DYNQOS

pytestmark = pytest.mark.timeout(120)

# Each command with the arguments it needs to get as far as reading its configuration.
COMMANDS = [
    ["config", "show"],
    ["config", "zenoh"],
    ["sim", "cell"],
    ["sim", "vehicle"],
    ["edge", "router"],
    ["edge", "mpc"],
    ["edge", "planner"],
    ["edge", "detector"],
    ["edge", "qos"],
    ["onboard"],
]
# These read no settings (a scenario, a profile or their own options say what they do), so a --config or
# --set given to them is refused rather than silently ignored.
READ_NO_SETTINGS = [
    ["demo"],
    ["run", "scenario.toml"],
    ["certs", "--out", "pki", "--drone", "uav1"],
    ["signing-key", "--out", "fc.key"],
    ["health", "health.json"],
    ["bench", "--smoke"],
    ["version"],
]
BAD_CONFIG = [
    (["--config", "/nonexistent/dynqos.toml"], "config file not found"),
    (["--set", "zenoh.default_port=0"], "zenoh.default_port: must be a TCP port"),
    (["--set", "zenoh.nope=1"], "zenoh.nope: unknown key"),
    (["--set", "supervisor.rho=[1, 2]"], "supervisor.rho"),
]


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c[:2]))
@pytest.mark.parametrize(
    ("extra", "message"), BAD_CONFIG, ids=["missing", "bad-value", "unknown-key", "bad-type"]
)
def test_bad_configuration_is_one_line_and_exit_2(
    command: list[str], extra: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # The configuration is read before any command acts, so in-process is safe: nothing starts.
    assert main([*command, *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith("dynqos: error: ")
    assert message in err


@pytest.mark.parametrize("command", READ_NO_SETTINGS, ids=lambda c: " ".join(c[:2]))
@pytest.mark.parametrize(("extra", "_"), BAD_CONFIG[:2], ids=["config", "set"])
def test_settings_given_to_a_command_that_reads_none_are_refused(
    command: list[str], extra: list[str], _: str, capsys: pytest.CaptureFixture[str]
) -> None:
    for argv in ([*command, *extra], [*extra, *command]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
        assert extra[0] in capsys.readouterr().err


@pytest.fixture
def busy_ports() -> Iterator[tuple[int, int, int]]:
    """Two TCP ports that refuse connections (bound, nothing listens) and one that is taken."""
    closed = [socket.socket(), socket.socket()]
    for sock in closed:
        sock.bind(("127.0.0.1", 0))
    taken = socket.create_server(("127.0.0.1", 0))
    try:
        yield closed[0].getsockname()[1], closed[1].getsockname()[1], taken.getsockname()[1]
    finally:
        for sock in [*closed, taken]:
            sock.close()


def _cases(closed: int, closed2: int, taken: int, tmp: Path) -> list[tuple[list[str], str]]:
    unreachable = ["--set", f"zenoh.default_port={closed}", "--set", "zenoh.connect_timeout_s=1"]
    camara = ["edge", "qos", "--set", "qos.backend=camara", "--set", "qos.camara.api_root=http://127.0.0.1:1"]
    return [
        (["edge", "mpc", *unreachable], "cannot open zenoh edge session"),
        (["edge", "planner", *unreachable], "cannot open zenoh edge session"),
        (["edge", "detector", *unreachable], "cannot open zenoh edge session"),
        (["edge", "qos", *unreachable], "cannot open zenoh edge session"),
        (["edge", "qos", "--set", "qos.backend=camara"], "qos.camara.api_root: is required"),
        (
            [
                *camara,
                "--set",
                "qos.camara.token_url=http://127.0.0.1:1/token",
                "--set",
                "qos.camara.client_id=x",
                "--set",
                f"qos.camara.client_secret_file={tmp / 'no-secret'}",
            ],
            "cannot read",
        ),
        ([*camara, "--set", "zenoh.edge_host=edge.example"], "is not an IP address"),
        (["sim", "cell", "--set", "cell.qod=true"], "needs a control port"),
        (
            ["sim", "cell", "--set", "cell.qod=true", "--set", "cell.qod_auth=true"],
            "needs [qos.camara] headers_file, or client_id",
        ),
        (
            ["onboard", *unreachable, "--set", f"zenoh.priority_port={closed2}"],
            "cannot open zenoh drone session",
        ),
        (["edge", "router", "--set", f"zenoh.default_port={taken}"], "cannot open zenoh router session"),
        (["sim", "cell", "--set", f"cell.default_listen_port={taken}"], "cannot listen on 127.0.0.1"),
        (["run", "/nonexistent/scenario.toml"], "scenario file not found"),
        (["bench", "nope"], "unknown benchmark nope"),
        (["health", "/nonexistent/health.json"], "no health file"),
        (["health", str(tmp)], "no health file"),  # a folder where the file should be
        (["certs", "--out", "/proc/dynqos-pki", "--drone", "uav1"], "cannot create /proc/dynqos-pki"),
        (["signing-key", "--out", "/proc/dynqos/fc.key"], "cannot write the signing key /proc/dynqos/fc.key"),
        (["onboard", "--set", 'onboard.mavlink_signing_key="/nonexistent/fc.key"'], "cannot read it"),
        (["sim", "vehicle", "--set", f'vehicle.signing_key="{tmp}"'], "not a regular file"),
        (["demo", "--duration", "-3"], "duration"),
        (["demo", "--scenario", "baseline", "--out", str(tmp / "a-file")], "cannot make the run folder"),
    ]


def _run(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([DYNQOS, *args], capture_output=True, text=True, timeout=60)


def test_unreachable_endpoints_and_bad_arguments_are_one_line_and_exit_2(
    busy_ports: tuple[int, int, int], tmp_path: Path
) -> None:
    (tmp_path / "a-file").write_text("not a folder")
    cases = _cases(*busy_ports, tmp_path)
    # four at a time: a fifth of them wait out a 1 s connect timeout, the rest are short processes
    with concurrent.futures.ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(_run, (args for args, _ in cases)))
    for (args, message), result in zip(cases, results, strict=True):
        lines = [line for line in result.stderr.splitlines() if not line[:4].isdigit()]  # log lines aside
        assert result.returncode == 2, (args, result.stderr[-1000:])
        assert len(lines) == 1, (args, result.stderr[-1000:])
        assert lines[0].startswith("dynqos: error: ")
        assert message in lines[0], (args, lines[0])
        assert "Traceback" not in result.stderr
