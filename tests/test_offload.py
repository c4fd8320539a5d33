"""A user's task served by `dynqos edge serve` as real processes on 127.0.0.1: bad task modules say one
line and exit 2; replicas share the drones and one answers them all when the other is killed."""

from __future__ import annotations

import math
import subprocess
import threading
from pathlib import Path

import pytest

from dynqos.common import keys
from dynqos.common.bus import Priority
from dynqos.common.config import ZenohConfig
from dynqos.common.messages import TaskAnswer, TaskRequest
from dynqos.common.queues import BoundedQueue
from dynqos.common.tasks import Codec, Edge, load
from dynqos.common.transport import Bus, Received, Role, open_bus
from dynqos.edge.replicas import ranked
from tests.procs import DYNQOS, DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = str(ROOT / "examples" / "look_at.py")

TASK_HEAD = "import msgspec\nfrom dynqos.offload import Edge, Task\n"
BAD_MODULES = {
    "raises.py:EDGE": ("raise RuntimeError('boom')\n", "failed to import", "RuntimeError: boom"),
    "wrong.py:EDGE": ("EDGE = 3\n", "EDGE is a int", "not a dynqos.offload.Edge or dynqos.offload.Service"),
    "rate.py:EDGE": (
        TASK_HEAD + "EDGE = Edge(Task('t', dict, dict, rate_hz=0, deadline_s=0.1), handle=print)\n",
        "task t: rate_hz must be",
        "",
    ),
    "name.py:EDGE": (TASK_HEAD + "EDGE = Edge(Task('T!', dict, dict, 10, 0.1), print)\n", "task name", ""),
    "service.py:EDGE": (
        TASK_HEAD.replace("Edge", "Service") + "EDGE = Service(Task('t', dict, dict, 10, 0.1), make=3)\n",
        "task t: Service.make must be callable",
        "",
    ),
    "missing.py:EDGE": (None, "no such file", ""),
    "noattr.py": ("X = 1\n", "name a task as MODULE:ATTR", ""),
}


@pytest.mark.parametrize("target", sorted(BAD_MODULES))
def test_a_task_that_does_not_load_or_declares_nonsense_says_one_line_and_exits_2(
    tmp_path: Path, target: str
) -> None:
    source, said, also = BAD_MODULES[target]
    if source is not None:
        (tmp_path / target.split(":")[0]).write_text(source)
    done = subprocess.run(
        [DYNQOS, "edge", "serve", str(tmp_path / target)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("dynqos: error:"), done.stderr
    assert said in lines[0]
    assert also in lines[0]
    assert "Traceback" not in done.stderr


def _ask_until_answered(
    bus: Bus, uavs: list[str], first_seq: int, timeout_s: float = 20.0
) -> dict[str, TaskAnswer]:
    """One request a drone (asked again every 0.2 s with a new seq until answered); the first answer of
    each drone, and every answer's count to check that none came twice for one request."""
    served: Edge[object, object] = load(f"{EXAMPLE}:EDGE", Edge)
    codec: Codec[object, object] = Codec(served.task)
    answers: BoundedQueue[Received] = BoundedQueue(1024)
    key = f"{keys.ROOT}/*/down/task/look-at"
    stats = bus.subscribe(key, answers, expect=(TaskAnswer,))
    pubs = {
        u: bus.publisher(keys.task_uplink(u, keys.Flow.DEFAULT, "look-at"), Priority.DATA_HIGH) for u in uavs
    }
    request_type = served.task.request
    got: dict[str, TaskAnswer] = {}
    seen: dict[tuple[str, int], int] = {}
    seq = first_seq
    done = threading.Event()
    timer = threading.Timer(timeout_s, done.set)
    timer.start()
    try:
        while not done.is_set() and len(got) < len(uavs):
            for i, uav in enumerate(uavs):
                if uav not in got:
                    body = codec.encode_request(request_type(pos_m=(float(i + 1), 1.0, -1.5)))  # type: ignore[call-arg]
                    pubs[uav].put(
                        TaskRequest(uav=uav, seq=seq, task="look-at", stamp_ns=0, budget_ms=500, body=body)
                    )
            seq += 1
            while (item := answers.get(0.2)) is not None:
                message = item.message
                assert isinstance(message, TaskAnswer)
                seen[(message.uav, message.seq)] = seen.get((message.uav, message.seq), 0) + 1
                got.setdefault(message.uav, message)
    finally:
        timer.cancel()
        bus.unsubscribe(key, stats)
    assert all(n == 1 for n in seen.values()), f"a request answered twice: {seen}"
    return got


def test_two_replicas_share_the_drones_and_one_answers_all_when_the_other_is_killed(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]],
) -> None:
    config, zcfg, procs = edge
    names = ("look-a", "look-b")
    for name in names:
        procs.append(DynqosProcess(["edge", "serve", f"{EXAMPLE}:EDGE", "--replica-id", name], config))
    serving = dict(zip(names, procs[-2:], strict=True))
    uavs = [f"uav{i}" for i in range(1, 9)]
    bus = open_bus(zcfg, Role.DRONE)
    try:
        got = _ask_until_answered(bus, uavs, first_seq=1)
        assert sorted(got) == sorted(uavs)
        for i, uav in enumerate(uavs):
            served = load(f"{EXAMPLE}:EDGE", Edge)
            body = Codec(served.task).decode_answer(got[uav].body)
            assert math.isclose(body.yaw_rad, math.atan2(-1.0, -(i + 1.0)), abs_tol=1e-9)  # type: ignore[attr-defined]
            assert got[uav].replica == ranked(uav, names)[0]  # each drone by the replica that ranks first
        serving["look-a"].proc.kill()
        serving["look-a"].stop()
        got = _ask_until_answered(bus, uavs, first_seq=1000)
        assert {a.replica for a in got.values()} == {"look-b"}
    finally:
        bus.close()
    log_b = serving["look-b"].stop()
    assert "replica look-a left" in log_b
