"""The harness that starts services for the end-to-end tests keeps a chatty child running: a service logs
a health line a second, and a pipe nobody reads stops it after 64 KiB (about 140 s of the onboard
daemon's log), which is how a long flight once went silent in CI."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.flights import fly_for_behaviour
from tests.procs import DynqosProcess

pytestmark = pytest.mark.timeout(60)

CHATTY = """
import json, sys, time
print(json.dumps({"ready": True}), flush=True)
for i in range(4000):
    print(f"health line {i} " + "x" * 500, file=sys.stderr, flush=True)  # 2 MB: 30 pipes' worth
print("and more on stdout " * 10000, flush=True)
print("finished", file=sys.stderr, flush=True)
time.sleep(60)
"""
TERSE = "import json, sys; print(json.dumps({}), flush=True); [print(i, file=sys.stderr) for i in range(5)]"


def test_a_child_that_logs_megabytes_is_not_blocked_and_its_log_tail_is_kept(tmp_path: Path) -> None:
    child = DynqosProcess(["-c", CHATTY], tmp_path / "unused.toml", executable=sys.executable)
    try:
        finished = any(line.strip() == "finished" for line in child.lines(timeout_s=20))
        assert child.alive()
    finally:
        log = child.stop()
    assert finished, "the child stopped writing: blocked on a full pipe"
    assert "health line 3999 " in log  # the tail is kept, bounded
    assert log.endswith("finished\n")


def test_lines_hands_out_the_log_as_it_comes_and_ends_with_the_child(tmp_path: Path) -> None:
    child = DynqosProcess(["-c", TERSE], tmp_path / "unused.toml", executable=sys.executable)
    try:
        assert [line.strip() for line in child.lines(timeout_s=20)] == ["0", "1", "2", "3", "4"]
    finally:
        child.stop()


def summaries(how: str, *flights: tuple[bool, bool]) -> Callable[[Path], dict[str, Any]]:
    """Made-up flights, one per (not its own, fell back) in order; `how` the cores were not its own:
    "starved" (its machine: not ok), "stolen" (the host) or "throttled" (a CPU quota: the verdict stands)."""
    queue = list(flights)

    def fly(out: Path) -> dict[str, Any]:
        taken, fell_back = queue.pop(0)
        starved = how == "starved" and taken
        machine = {
            "starved": starved,
            "stolen": how == "stolen" and taken,
            "throttled": how == "throttled" and taken,
        }
        failure = "starved: busy" if starved else ""
        return {"ok": not starved, "failure": failure, "machine": machine, "fb": fell_back, "out": out.name}

    return fly


def check(summary: dict[str, Any], _: Path) -> None:
    assert not summary["fb"], "fell back"


@pytest.mark.parametrize("how", ["starved", "stolen", "throttled"])
def test_a_behaviour_test_flies_again_only_when_it_failed_on_cores_not_its_own(
    tmp_path: Path, how: str
) -> None:
    """tests/flights.py: a flight that behaved on cores not its own (starved by its machine, stolen by the
    host: steal above a tenth, or held by its container's CPU quota) passes; one that broke the check on
    them is flown again and its second flight decides; one that broke it with cores to spare fails at
    once."""
    assert fly_for_behaviour(summaries(how, (True, False)), tmp_path, check)["out"] == "first"
    assert fly_for_behaviour(summaries(how, (True, True), (False, False)), tmp_path, check)["out"] == "again"
    with pytest.raises(AssertionError, match="fell back"):
        fly_for_behaviour(summaries(how, (True, True), (True, True)), tmp_path, check)
    with pytest.raises(AssertionError, match="fell back"):
        fly_for_behaviour(summaries(how, (False, True), (False, False)), tmp_path, check)
