"""The edge_scale benchmark's verdict (bench/edge_scale.py): what it judges from a sweep's runs, so a
larger host's eight replicas are held to their own target and not passed on two replicas alone; and
how it reads its load processes."""

from __future__ import annotations

import contextlib
import io
import subprocess
from collections.abc import Iterator
from typing import Any, cast

import pytest

from dynqos.bench import edge_scale
from dynqos.bench.edge_scale import _Lines, verdict


def _run(mode: str, processes: int, served: int, cpu_over_one: float | None = None) -> dict[str, Any]:
    return {
        "mode": mode,
        "processes": processes,
        "max_drones_at_20hz": served,
        "mpc_cpu_per_drone_over_one": cpu_over_one,
    }


def _result(*runs: dict[str, Any]) -> dict[str, Any]:
    return {"cores": 16, "runs": [_run("one", 1, 100, 1.0), *runs]}


def test_two_replicas_are_judged_on_drones_and_cpu() -> None:
    assert verdict(_result(_run("replicas", 2, 100, 1.25))).startswith("meets")
    assert verdict(_result(_run("replicas", 2, 75, 1.25))).startswith("misses")  # fewer than one
    assert verdict(_result(_run("replicas", 2, 100, 1.4))).startswith("misses")  # CPU over 1.3x


def test_eight_replicas_must_serve_six_times_one_and_at_least_600() -> None:
    two = _run("replicas", 2, 100, 1.2)
    said = verdict(_result(two, _run("replicas", 8, 400)))
    assert said.startswith("misses")
    assert "eight replicas serve 400 drones, 4.0x" in said
    assert verdict(_result(two, _run("replicas", 8, 600))).startswith("meets")
    small = {"cores": 16, "runs": [_run("one", 1, 50, 1.0), two, _run("replicas", 8, 400)]}
    assert verdict(small).startswith("misses")  # 8x one's, but under 600


def test_a_sweep_without_one_process_cannot_be_judged() -> None:
    assert "needs one process" in verdict({"cores": 2, "runs": [_run("replicas", 2, 100, 1.0)]})


class _Said:
    def __init__(self, text: str) -> None:
        self.stdout = io.StringIO(text)


def test_a_load_process_that_measured_and_ended_before_another_began_is_waited_for_not_an_error() -> None:
    """On a slow host one load process may settle, measure and end before another settles: what it
    said before its end still counts (it once read as "ended before it said 'measuring'")."""
    early = "ready\nmeasuring\ndone\n{}\n"
    lines = _Lines(cast(list[subprocess.Popen[str]], [_Said(early), _Said(early)]))
    lines.until("ready", every=True, timeout_s=5)
    lines.until("measuring", every=True, timeout_s=5)
    lines.until("done", every=True, timeout_s=5)
    lines.until("{", every=True, timeout_s=5)
    assert [said[-1] for said in lines.said] == ["{}", "{}"]


def test_mpc_settings_reach_every_mpc_process_and_a_bad_one_is_refused_before_any_starts(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    started: list[list[str]] = []

    class Procs:
        def start(self, name: str, args: list[str]) -> None:
            started.append(args)

    @contextlib.contextmanager
    def rig(extra: str) -> Iterator[tuple[None, Procs]]:
        yield None, Procs()

    row = {"drones": 10, "served": True, "answered": 1.0, "p99_ms": 5.0, "mpc_core_share_per_drone": 0.01}
    monkeypatch.setattr(edge_scale, "router_rig", rig)
    monkeypatch.setattr(edge_scale, "fleet", lambda *_: dict(row))
    result = edge_scale.run([1, 2], ["replicas"], [10], 1, 1.0, settings=("mpc.standby_reads=copies",))
    assert len(started) == 3  # one process, then two replicas
    assert all(args[-2:] == ["--set", "mpc.standby_reads=copies"] for args in started), started
    assert result["mpc_settings"] == ["mpc.standby_reads=copies"]
    with pytest.raises(SystemExit) as stop:
        edge_scale.main(["--quick", "--mpc-set", "mpc.standby_reads=nope"])
    assert stop.value.code == 2
    assert "--mpc-set: --set: mpc.standby_reads: 'nope' is not one of" in capsys.readouterr().err
    assert len(started) == 3  # nothing more started
