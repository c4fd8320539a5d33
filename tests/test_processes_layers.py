"""A flight's processes stop a layer at a time: the last one started first, then the ones a `together`
started (or that joined a layer with `stop_with`) all at once, then the ones before. Each process here
is a real child that says ready, and on SIGTERM notes when, lingers 0.4 s, notes when it left."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from dynqos.experiment.processes import Processes

pytestmark = pytest.mark.timeout(60)

CHILD = """
import json, signal, sys, time
log = sys.argv[1]
def stop(*_):
    with open(log, "a") as f:
        f.write(f"term {time.monotonic()}\\n")
    time.sleep(0.4)
    with open(log, "a") as f:
        f.write(f"gone {time.monotonic()}\\n")
    sys.exit(0)
signal.signal(signal.SIGTERM, stop)
print(json.dumps({"ready": True}), flush=True)
while True:
    time.sleep(1)
"""


def _times(path: Path) -> dict[str, float]:
    return {word: float(t) for word, t in (line.split() for line in path.read_text().splitlines())}


def test_each_layer_stops_at_once_and_the_last_layer_first(tmp_path: Path) -> None:
    config = tmp_path / "dynqos.toml"
    config.write_text("")
    procs = Processes(config, tmp_path)
    logs = {name: tmp_path / f"{name}.times" for name in ("router", "a", "b", "drone1", "drone2")}

    def start(name: str, stop_with: str | None = None) -> None:
        program = [sys.executable, "-c", CHILD, str(logs[name])]
        procs.start(name, [], program=program, stop_with=stop_with)

    try:
        start("router")
        with procs.together():
            start("a")
            start("b")
        start("drone1")
        start("drone2", stop_with="drone1")
    finally:
        began = time.monotonic()
        codes = procs.stop_all()
    assert set(codes.values()) == {0}
    t = {name: _times(path) for name, path in logs.items()}
    # three layers of 0.4 s each, not five processes one after another
    assert time.monotonic() - began < 5 * 0.4
    assert max(t["drone1"]["gone"], t["drone2"]["gone"]) <= min(t["a"]["term"], t["b"]["term"])
    assert max(t["a"]["gone"], t["b"]["gone"]) <= t["router"]["term"]
    # within a layer, each was told before any had gone
    assert max(t["a"]["term"], t["b"]["term"]) < min(t["a"]["gone"], t["b"]["gone"])
    assert max(t["drone1"]["term"], t["drone2"]["term"]) < min(t["drone1"]["gone"], t["drone2"]["gone"])
