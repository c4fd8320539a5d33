"""Prometheus metrics and /healthz (common/metrics.py, onboard/metrics.py, edge/metrics.py,
docs/observability.md): the pure parts with crafted inputs, the endpoint over real HTTP on 127.0.0.1,
and (slow) every service of a real flight scraped while it flies and parsed with prometheus-client's
own parser."""

from __future__ import annotations

import json
import queue
import re
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from dynqos.common.bus import MemoryBus
from dynqos.common.config import MetricsConfig, load_config
from dynqos.common.errors import DynqosError
from dynqos.common.messages import State, SupervisorStatus, encode
from dynqos.common.metrics import HealthBeat, ProcessMetrics, bus_families
from dynqos.common.queues import BoundedQueue
from dynqos.onboard.commands import CommandCounters
from dynqos.onboard.metrics import DroneMetrics
from tests.conftest import free_tcp_port
from tests.procs import DYNQOS
from tests.statuses import status

pytestmark = pytest.mark.timeout(60)

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def _samples(text: str) -> Samples:
    """Every sample as {(name, sorted labels): value}, through prometheus-client's parser."""
    out: Samples = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            out[(sample.name, tuple(sorted(sample.labels.items())))] = sample.value
    return out


def _value(samples: Samples, name: str, **labels: str) -> float:
    return samples[(name, tuple(sorted(labels.items())))]


def _status(
    state: str, *, prev: str = "q1", cause: str = "", changed_ns: int = 0, **extra: Any
) -> SupervisorStatus:
    return status(state=state, p_lat=0.25, prev_state=prev, cause=cause, changed_ns=changed_ns, **extra)


def test_the_health_beat_is_fresh_then_stale_on_its_clock() -> None:
    now = [100.0]
    beat = HealthBeat(10.0, clock=lambda: now[0])
    assert beat.status() == (False, "starting: no health line yet")
    beat.beat("drones=1")
    assert beat.status() == (True, "drones=1")
    now[0] += 10.0
    assert beat.status()[0]
    now[0] += 0.5
    ok, text = beat.status()
    assert not ok
    assert text.startswith("stale: last health line 10 s ago")


def test_drone_metrics_follow_the_statuses_they_are_handed() -> None:
    metrics = ProcessMetrics("onboard", MetricsConfig())
    counters = CommandCounters(accepted=7, stale=2)
    drone = DroneMetrics("uav1", metrics, counters, None)
    drone.observe(_status("q1", rtt_samples_ms=(14.0, 16.0), camera_latency_samples_ms=(30.0,)))
    drone.observe(_status("q1", rtt_samples_ms=(15.0,)))
    drone.observe(
        _status("q3", prev="q1", cause="MR and HL", changed_ns=5, flow="priority", rtt_samples_ms=(60.0,))
    )
    drone.observe(_status("q3", prev="q1", cause="MR and HL", changed_ns=5, flow="priority"))  # no new change
    samples = _samples(generate_latest(metrics.registry).decode())
    assert _value(samples, "dynqos_cc_rtt_seconds_count", uav="uav1") == 4
    assert (
        _value(samples, "dynqos_cc_rtt_seconds_bucket", uav="uav1", le="0.015") == 2
    )  # 14 and 15 ms (le: <=)
    assert _value(samples, "dynqos_cc_rtt_seconds_sum", uav="uav1") == pytest.approx(0.105)
    assert _value(samples, "dynqos_camera_latency_seconds_count", uav="uav1") == 1
    assert _value(samples, "dynqos_supervisor_state", uav="uav1", state="q3") == 1
    assert _value(samples, "dynqos_supervisor_state", uav="uav1", state="q1") == 0
    assert _value(samples, "dynqos_flow", uav="uav1", flow="priority") == 1
    transitions = "dynqos_supervisor_transitions_total"
    assert _value(samples, transitions, uav="uav1", from_state="q1", to_state="q3", cause="MR and HL") == 1
    assert _value(samples, "dynqos_latency_probability", uav="uav1") == 0.25
    assert _value(samples, "dynqos_commands_accepted_total", uav="uav1") == 7
    assert _value(samples, "dynqos_commands_rejected_total", uav="uav1", cause="stale") == 2
    assert (
        _value(samples, "dynqos_build_info", version=__import__("dynqos").__version__, service="onboard") == 1
    )


def test_a_drones_offloaded_tasks_are_counted_by_task_and_say_when_they_fall_back() -> None:
    metrics = ProcessMetrics("onboard", MetricsConfig())
    drone = DroneMetrics("uav1", metrics, CommandCounters(), None)
    drone.observe(_status("q1"))
    before = _samples(generate_latest(metrics.registry).decode())
    drone.observe(_status("q1", tasks=(("look-at", "fallback", 40, 35, 5, 0.5, (12.0,)),)))
    samples = _samples(generate_latest(metrics.registry).decode())
    assert not any(name.startswith("dynqos_task") for name, _labels in before)  # none without tasks
    assert _value(samples, "dynqos_task_calls_total", uav="uav1", task="look-at", event="requests") == 40
    assert _value(samples, "dynqos_task_calls_total", uav="uav1", task="look-at", event="misses") == 5
    assert _value(samples, "dynqos_task_fallback", uav="uav1", task="look-at") == 1


def test_bus_metrics_count_received_and_rejected_by_cause() -> None:
    bus = MemoryBus()
    sink: BoundedQueue[Any] = BoundedQueue(16)
    bus.subscribe("dynqos/*/up/*/state", sink, expect=(State,))
    state = State(uav="uav1", seq=1, stamp_ns=1, pos_m=(0, 0, 0), vel_mps=(0, 0, 0), quat=(1, 0, 0, 0))
    bus.deliver("dynqos/uav1/up/default/state", encode(state))
    bus.deliver("dynqos/uav2/up/default/state", encode(state))  # uav1 speaking on uav2's key
    bus.deliver("dynqos/uav1/up/default/state", b"\x00garbage")
    bus.deliver("dynqos/uav1/up/default/state", encode(_status("q1")))
    metrics = ProcessMetrics("mpc", MetricsConfig())
    metrics.add(lambda: bus_families(bus))
    samples = _samples(generate_latest(metrics.registry).decode())
    key = "dynqos/*/up/*/state"
    assert _value(samples, "dynqos_messages_received_total", key=key) == 1
    for cause in ("wrong_drone", "undecodable", "unexpected_type"):
        assert _value(samples, "dynqos_messages_rejected_total", key=key, cause=cause) == 1


def _get(url: str) -> tuple[int, str]:
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return response.status, response.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def test_the_endpoint_serves_metrics_and_healthz_and_says_when_its_port_is_taken() -> None:
    port = free_tcp_port()
    metrics = ProcessMetrics("planner", MetricsConfig(port=port))
    assert metrics.start() == port
    try:
        status, text = _get(f"http://127.0.0.1:{port}/healthz")
        assert (status, text) == (503, "planner: starting: no health line yet\n")
        metrics.health.beat("drones=0 references=0")
        assert _get(f"http://127.0.0.1:{port}/healthz") == (200, "planner: drones=0 references=0\n")
        status, text = _get(f"http://127.0.0.1:{port}/metrics")
        assert status == 200
        assert ("dynqos_build_info", (("service", "planner"), ("version", "0.1.0"))) in _samples(text)
        with pytest.raises(DynqosError, match=f"cannot listen on 127.0.0.1:{port}"):
            ProcessMetrics("mpc", MetricsConfig(port=port)).start()
    finally:
        metrics.stop()
    assert ProcessMetrics("mpc", MetricsConfig()).start() is None  # port 0: off


def test_bad_metrics_options_are_one_line_and_exit_2() -> None:
    out = subprocess.run(
        [DYNQOS, "edge", "planner", "--metrics-port", "70000"], capture_output=True, text=True, timeout=30
    )
    assert out.returncode == 2
    assert out.stderr.strip().startswith("dynqos: error: --metrics-port/--metrics-host: port:")


def _scrape(port: int) -> Samples:
    status, text = _get(f"http://127.0.0.1:{port}/metrics")
    assert status == 200
    return _samples(text)


def _wait_for_health(port: int, deadline: float) -> None:
    """A service's /healthz turns 200 once it has written its first health line (bounded poll: another
    process's HTTP endpoint has no event to await)."""
    while time.monotonic() < deadline:
        try:
            if _get(f"http://127.0.0.1:{port}/healthz")[0] == 200:
                return
        except OSError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"port {port}: /healthz never answered 200")


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(240)
def test_every_service_of_a_flight_is_scraped_while_it_flies(tmp_path: Path) -> None:
    from dynqos.common.transport import Role, open_session

    base = free_tcp_port()
    while any(_port_taken(base + i) for i in range(8)):
        base = free_tcp_port()
    run = subprocess.Popen(
        [DYNQOS, "run", "dynqos/scenarios/bg-dynqos.toml", "--duration", "25", "--metrics-port", str(base),
         "--out", str(tmp_path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1],
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        ports = _ports_when_flying(tmp_path, deadline, run)
        for name, port in ports.items():
            _wait_for_health(port, deadline)
            assert (
                _value(_scrape(port), "dynqos_build_info", version="0.1.0", service=name.split("-")[0]) == 1
            )
        config = load_config(next(tmp_path.glob("*/dynqos.toml")))
        session = open_session(config.zenoh, Role.EDGE)
        statuses: queue.Queue[SupervisorStatus] = queue.Queue()
        from dynqos.common.messages import decode

        def on_status(sample: Any) -> None:
            message = decode(bytes(sample.payload))
            if isinstance(message, SupervisorStatus):
                statuses.put(message)

        subscriber = session.declare_subscriber("dynqos/uav1/up/*/status", on_status)
        try:
            _check_the_drone(ports["onboard"], statuses)
        finally:
            subscriber.undeclare()
            session.close()  # type: ignore[no-untyped-call]
        _check_the_edge_and_the_cell(ports)
        exposed = set().union(*(_families(port) for port in ports.values()))
        documented = {re.sub(r"_total$", "", name) for name in _documented_metrics()}
        assert documented - exposed == set()  # docs/observability.md lists only what is served
        assert exposed - documented - {"dynqos_build_info"} == set()  # and everything that is
    finally:
        if run.poll() is None:
            run.send_signal(2)  # the run's own SIGINT path: stops every process it started
        _, err = run.communicate(timeout=90)
    assert run.returncode in (0, 1), err[-2000:]


def _families(port: int) -> set[str]:
    """Family names as prometheus-client's parser gives them (counters without `_total`)."""
    _, text = _get(f"http://127.0.0.1:{port}/metrics")
    return {family.name for family in text_string_to_metric_families(text)}


def _documented_metrics() -> set[str]:
    text = (Path(__file__).resolve().parents[1] / "docs" / "observability.md").read_text()
    return set(re.findall(r"^\| `(dynqos_[a-z_]+)`", text, re.M))


def _port_taken(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _ports_when_flying(folder: Path, deadline: float, run: subprocess.Popen[str]) -> dict[str, int]:
    """The services' metrics ports once the run has started its drone; a run that ended first fails at
    once with what it said, and one still starting at the deadline with what its processes logged."""
    while time.monotonic() < deadline:
        found = list(folder.glob("*/logs/metrics.json"))
        if found:
            ports: dict[str, int] = json.loads(found[0].read_text())
            if "onboard" in ports:
                return ports
        if run.poll() is not None:
            said = run.stderr.read()[-2000:] if run.stderr else ""
            raise AssertionError(f"the run ended ({run.returncode}) before its drone started: {said}")
        time.sleep(0.2)
    logs = {log.name: log.read_text()[-300:] for log in folder.glob("*/logs/*.log")}
    raise AssertionError(f"the run never started the drone; its logs end: {logs}")


def _latest(statuses: queue.Queue[SupervisorStatus], after: int) -> list[SupervisorStatus]:
    """At least `after` more statuses (each comes a few times a second: an event to await)."""
    got = [statuses.get(timeout=10) for _ in range(after)]
    while not statuses.empty():
        got.append(statuses.get_nowait())
    return got


def _check_the_drone(port: int, statuses: queue.Queue[SupervisorStatus]) -> None:
    first = _scrape(port)
    count = _value(first, "dynqos_cc_rtt_seconds_count", uav="uav1")
    _latest(statuses, 5)
    again = _scrape(port)
    assert _value(again, "dynqos_cc_rtt_seconds_count", uav="uav1") > count  # the RTT histogram grows
    assert _value(again, "dynqos_commands_accepted_total", uav="uav1") > 0
    for _ in range(20):  # the scraped state is the one the drone published, when none changed meanwhile
        before = _latest(statuses, 1)[-1]
        scraped = _scrape(port)
        after = _latest(statuses, 1)[-1]
        if before.changed_ns == after.changed_ns and before.state == after.state:
            state = after.state.value
            assert _value(scraped, "dynqos_supervisor_state", uav="uav1", state=state) == 1
            others = [v for (name, labels), v in scraped.items() if name == "dynqos_supervisor_state"]
            assert sum(others) == 1
            assert _value(scraped, "dynqos_flow", uav="uav1", flow=after.flow.value) == 1
            return
    raise AssertionError("the supervisor changed state at every scrape")


def _check_the_edge_and_the_cell(ports: dict[str, int]) -> None:
    mpc = _scrape(ports["mpc"])
    assert _value(mpc, "dynqos_mpc_solve_seconds_count") > 0
    assert _value(mpc, "dynqos_mpc_drones") == 1
    assert _value(mpc, "dynqos_messages_received_total", key="dynqos/*/up/*/state") > 0
    assert _value(_scrape(ports["planner"]), "dynqos_planner_references_total") > 0
    assert _value(_scrape(ports["detector"]), "dynqos_detector_events_total", event="frames") > 0
    assert _value(_scrape(ports["qos"]), "dynqos_qos_drones") == 1
    assert _value(_scrape(ports["router"]), "dynqos_router_links") >= 2
    cell = _scrape(ports["cell"])
    delivered = [
        v
        for (name, labels), v in cell.items()
        if name == "dynqos_cell_bytes_total" and ("kind", "delivered") in labels
    ]
    assert sum(delivered) > 0  # the drone's bearers carried its traffic
    assert _value(cell, "dynqos_cell_scale") == 10
    assert any(name == "dynqos_cell_queue_delay_seconds" for name, _ in cell)
