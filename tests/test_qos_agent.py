"""`dynqos edge qos` as a real process between a test drone (a zenoh session on 127.0.0.1) and the
emulated operator (`dynqos sim cell` serving the QoD API): what the drone is told, which sessions exist,
and that none is left behind, with each backend."""

from __future__ import annotations

import contextlib
import http.server
import json
import signal
import subprocess
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Priority, Publisher, Received, Role, open_bus
from tests.conftest import flow_ports, free_tcp_port
from tests.procs import DYNQOS, DynqosProcess, start_together

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

UAV = "uav1"
ADDRESSES = 'api_version = "1.2.0"\napplication_server_addresses = ["127.0.0.1", "127.0.0.2"]\n'


@dataclass
class Rig:
    config: Path
    zenoh: ZenohConfig
    cell_port: int
    procs: dict[str, DynqosProcess]

    def counters(self) -> dict[str, Any]:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.cell_port}/counters", timeout=5) as r:
            out: dict[str, Any] = json.loads(r.read())
            return out

    def sessions(self) -> list[dict[str, Any]]:
        sessions: list[dict[str, Any]] = self.counters()["qod"]["sessions"]
        return sessions

    def granted(self) -> bool:
        return bool(self.counters()["bearers"][f"{UAV}-priority"]["granted"])

    def event(self, **event: Any) -> str:
        """A timeline event applied now through the cell's control API."""
        request = urllib.request.Request(
            f"http://127.0.0.1:{self.cell_port}/events", json.dumps(event).encode(), method="POST"
        )
        with urllib.request.urlopen(request, timeout=5) as r:
            applied: str = json.loads(r.read())["applied"]
            return applied


# [qos.camara] keys every rig sets, unless its own lines set them
CAMARA_DEFAULTS = (
    "duration_s = 4",
    "extend_before_s = 2",
    "poll_interval_s = 0.05",
    "retry_after_denied_s = 0.5",
)


def write_config(
    path: Path, zcfg: ZenohConfig, cell_port: int, backend: str, cell: str = "", camara: str = ""
) -> None:
    path.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        f"[cell]\nqod = true\ncontrol_port = {cell_port}\ndefault_listen_port = 0\npriority_listen_port = 0\n"
        f"qod_setup_s = 0.1\n{cell}"
        f'[qos]\nbackend = "{backend}"\nhold_down_s = 0.5\ngrant_interval_s = 0.2\nagent_timeout_s = 1.0\n'
        "drone_timeout_s = 2.0\nrequest_interval_s = 0.2\nhealth_interval_s = 1.0\n"
        f'[qos.camara]\napi_root = "http://127.0.0.1:{cell_port}/quality-on-demand/v1"\n'
        + "".join(f"{line}\n" for line in CAMARA_DEFAULTS if line.split(" =")[0] + " =" not in camara)
        + camara
        + f'[qos.camara.devices]\n{UAV} = {{ phoneNumber = "+46700000001" }}\n'
    )


@pytest.fixture
def rig(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Rig]:
    backend, cell, camara = (*getattr(request, "param", ("camara", "")), "")[:3]
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    config = tmp_path / "qos.toml"
    write_config(config, zcfg, cell_port, backend, cell, camara)
    with running(config, zcfg, cell_port) as started:
        yield started


@contextlib.contextmanager
def running(config: Path, zcfg: ZenohConfig, cell_port: int) -> Iterator[Rig]:
    """The router, the emulated cell and the agent with `config`; each stopped by its pid after."""
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router"], procs["cell"] = start_together(config, ["edge", "router"], ["sim", "cell"])
        procs["agent"] = DynqosProcess(["edge", "qos"], config)
        yield Rig(config, zcfg, cell_port, procs)
    finally:
        for proc in reversed(list(procs.values())):
            proc.stop()


class Drone:
    """What the onboard daemon does for QoS, by hand: ask, and listen to the grants."""

    def __init__(self, zcfg: ZenohConfig) -> None:
        self.bus: Bus = open_bus(zcfg, Role.DRONE)
        self.grants: BoundedQueue[Received] = BoundedQueue(1000)
        self.bus.subscribe(keys.downlink(UAV, Downlink.QOS_GRANT), self.grants, expect=(QosGrant,))
        self.pub: Publisher = self.bus.publisher(
            keys.uplink(UAV, Flow.PRIORITY, Stream.QOS), Priority.DATA_HIGH
        )
        assert self.pub.wait_matched(20), "the agent never subscribed"
        self.seq = 0
        self.last: QosGrant | None = None

    def ask(self, want: bool) -> None:
        self.seq += 1
        self.pub.put(QosRequest(uav=UAV, seq=self.seq, stamp_ns=time.monotonic_ns(), want=want))

    def until(
        self, want: bool, grant: Grant, timeout_s: float = 15.0, also: Callable[[], bool] = lambda: True
    ) -> QosGrant:
        """Keep asking (as the drone repeats its request) until the agent's grant is `grant`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.ask(want)
            item = self.grants.get(0.2)  # the request interval; a grant wakes it at once
            while item is not None:
                assert isinstance(item.message, QosGrant)
                self.last = item.message
                item = self.grants.get_nowait()
            if self.last is not None and self.last.grant is grant and also():
                return self.last
        raise AssertionError(f"no {grant.value} grant within {timeout_s} s; last: {self.last}")

    def close(self) -> None:
        self.bus.close()


@pytest.fixture
def drone(rig: Rig) -> Iterator[Drone]:
    d = Drone(rig.zenoh)
    try:
        yield d
    finally:
        d.close()


def test_camara_a_drone_gets_a_session_while_it_wants_priority_and_none_after(rig: Rig, drone: Drone) -> None:
    granted = drone.until(True, Grant.AVAILABLE, also=rig.granted)
    assert granted.backend == "camara"
    assert granted.session_id
    (session,) = rig.sessions()
    assert session["sessionId"] == granted.session_id
    assert session["qosStatus"] == "AVAILABLE"
    assert session["applicationServerPorts"] == {"ports": [rig.zenoh.priority_port]}
    # duration 4 s, extended 2 s before it ends while still wanted: alive after 5 s
    drone.until(True, Grant.AVAILABLE, also=lambda: rig.counters()["qod"]["extended"] >= 1)
    assert rig.sessions()[0]["sessionId"] == granted.session_id
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])  # after the hold-down
    assert not rig.granted()
    counters = rig.counters()["qod"]
    assert (counters["created"], counters["deleted"]) == (1, 1)


def test_camara_sigterm_deletes_the_sessions_it_holds(rig: Rig, drone: Drone) -> None:
    drone.until(True, Grant.AVAILABLE)
    assert len(rig.sessions()) == 1
    rig.procs["agent"].proc.send_signal(signal.SIGTERM)
    assert rig.procs["agent"].proc.wait(timeout=20) == 0
    assert rig.sessions() == []
    err = rig.procs["agent"].stop()
    assert "deleted (stopping)" in err


def test_camara_a_restarted_agent_cleans_what_a_crashed_one_left(rig: Rig, drone: Drone) -> None:
    first = drone.until(True, Grant.AVAILABLE)
    rig.procs["agent"].proc.kill()  # a crash: no clean-up
    rig.procs["agent"].proc.wait(timeout=10)
    rig.procs["agent"].stop()
    assert [s["sessionId"] for s in rig.sessions()] == [first.session_id]  # left behind
    rig.procs["agent"] = DynqosProcess(["edge", "qos"], rig.config)
    again = drone.until(True, Grant.AVAILABLE, also=lambda: len(rig.sessions()) == 1)
    assert again.session_id != first.session_id
    assert [s["sessionId"] for s in rig.sessions()] == [again.session_id]
    rig.procs["agent"].proc.send_signal(signal.SIGTERM)
    rig.procs["agent"].proc.wait(timeout=20)
    assert "left by an earlier agent" in rig.procs["agent"].stop()
    assert rig.sessions() == []


SINK_PORT = free_tcp_port()
SINK = f'sink = "http://127.0.0.1:{SINK_PORT}/qod-events"\nsink_listen = "127.0.0.1:{SINK_PORT}"\n'


@pytest.mark.parametrize(
    "rig", [("camara", ""), ("camara", "", SINK)], indirect=True, ids=["polling", "sink"]
)
def test_camara_the_network_ending_a_session_is_told_and_asked_again(rig: Rig, drone: Drone) -> None:
    drone.until(True, Grant.AVAILABLE)
    end = json.dumps({"kind": "qod_end", "uav": UAV}).encode()
    url = f"http://127.0.0.1:{rig.cell_port}/events"
    headers = {"Content-Type": "application/json"}
    urllib.request.urlopen(urllib.request.Request(url, data=end, headers=headers), timeout=5)
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "NETWORK_TERMINATED" in told.reason
    drone.until(True, Grant.AVAILABLE)  # after the back-off, a new session
    counters = rig.counters()["qod"]
    assert counters["terminated"] == 1
    if "sink" in rig.config.read_text():  # the agent took the operator's notifications at its sink
        assert counters["notified"] >= 2
        assert counters["notify_failures"] == 0


@pytest.mark.parametrize("rig", [("camara", "qod_max_sessions = 0\n")], indirect=True)
def test_camara_an_operator_that_refuses_is_an_unavailable_grant_with_its_reason(
    rig: Rig, drone: Drone
) -> None:
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "NETWORK_TERMINATED" in told.reason
    assert not rig.granted()
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])  # what it asked for is cleaned up
    assert rig.counters()["qod"]["refused"] >= 1


def refused_at_start(config: Path, key: str) -> str:
    """Start the agent with `config`, expecting it to refuse before it serves: exit 2, no ready line, no
    traceback, and one error line naming `key`, returned."""
    agent = subprocess.run(
        [DYNQOS, "edge", "qos", "--config", str(config)], capture_output=True, text=True, timeout=60
    )
    assert agent.returncode == 2, agent.stderr[-2000:]
    assert agent.stdout == ""  # never said ready
    assert "Traceback" not in agent.stderr
    errors = [line for line in agent.stderr.splitlines() if key in line]
    assert len(errors) == 1, agent.stderr[-2000:]
    return errors[0]


def test_camara_a_profile_the_operator_does_not_offer_stops_the_agent_before_it_serves(
    tmp_path: Path,
) -> None:
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    config = tmp_path / "qos.toml"
    write_config(config, zcfg, cell_port, "camara", 'qod_inactive_profiles = ["QOS_M"]\n')
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router"], procs["cell"] = start_together(config, ["edge", "router"], ["sim", "cell"])
        for name, why in (("QOS_Z", "QOS_Z is not offered (offered: QOS_E, QOS_L, QOS_M, QOS_S)"),
                          ("QOS_M", "QOS_M is INACTIVE")):  # fmt: skip
            text = config.read_text().replace("[qos.camara]\n", f'[qos.camara]\nqos_profile = "{name}"\n', 1)
            (tmp_path / f"{name}.toml").write_text(text)
            assert why in refused_at_start(tmp_path / f"{name}.toml", "qos.camara.qos_profile")
        assert Rig(config, zcfg, cell_port, procs).counters()["qod"]["created"] == 0
    finally:
        for proc in reversed(list(procs.values())):
            proc.stop()


@pytest.mark.parametrize("rig", [("camara", "qod_max_duration_s = 3\n")], indirect=True)
def test_camara_a_duration_past_the_profiles_maximum_is_fitted_before_the_first_session(
    rig: Rig, drone: Drone
) -> None:
    granted = drone.until(True, Grant.AVAILABLE, also=rig.granted)  # asks for 4 s, the profile allows 3
    (session,) = rig.sessions()
    assert session["duration"] == 3
    assert session["sessionId"] == granted.session_id
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])
    log = rig.procs.pop("agent").stop()
    assert "profile QOS_E is ACTIVE, 1..3 s: asking for 3 s, not 4" in log


@pytest.mark.parametrize(
    ("rig", "flight_s"),
    [
        (("camara", "qod_max_duration_s = 6\n", "renew_before_s = 1\n"), 15.0),
        pytest.param(
            ("camara", "qod_profile_max_duration_s = { QOS_E = 10 }\n", "duration_s = 600\n"),
            30.0,
            marks=[pytest.mark.slow, pytest.mark.timeout(150)],
        ),
    ],
    indirect=["rig"],
    ids=["cap-6s", "cap-10s-30s-flight"],
)
def test_camara_an_operator_that_caps_sessions_gets_renewals_not_an_extend_storm(
    rig: Rig, drone: Drone, flight_s: float
) -> None:
    """An operator capping each session at its profile's maxDuration (6 s; 10 s in the slow case, the
    agent asking for 600 s and fitting it to 10 by the profile): each session is extended at most once
    more than the cap allows, replaced shortly before it ends, and the drone holds an AVAILABLE grant
    nearly all the time it wants one. Before the cap was recognised, each capped extend was due again
    at once (about 1000 calls in 20 s)."""
    drone.until(True, Grant.AVAILABLE)
    start = time.monotonic()
    since, state, available_s = start, Grant.AVAILABLE, 0.0
    while time.monotonic() - start < flight_s:
        drone.ask(True)
        item = drone.grants.get(0.2)
        while item is not None:
            assert isinstance(item.message, QosGrant)
            now = time.monotonic()
            available_s += (now - since) if state is Grant.AVAILABLE else 0.0
            since, state = now, item.message.grant
            item = drone.grants.get_nowait()
    wanted_s = time.monotonic() - start
    available_s += (time.monotonic() - since) if state is Grant.AVAILABLE else 0.0
    counters = rig.counters()["qod"]
    cap_s = 6.0 if flight_s < 30 else 10.0
    assert counters["created"] >= wanted_s // cap_s, counters  # renewed, not left to expire once
    assert counters["extended"] <= 2 * counters["created"], counters  # as asked, then one capped
    assert available_s >= 0.95 * wanted_s, (available_s, wanted_s)
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])
    log = rig.procs.pop("agent").stop()
    assert "before it ends" in log
    assert "renewing" in log


@pytest.mark.parametrize("rig", [("camara", "", "profile_recheck_s = 1\n")], indirect=True)
def test_camara_a_profile_the_operator_makes_inactive_mid_flight_stops_new_sessions_until_it_is_back(
    rig: Rig, drone: Drone
) -> None:
    """The operator makes QOS_E INACTIVE while a drone holds a session: the session runs on; once it is
    released, asking again is told UNAVAILABLE naming the profile, with no create made; when the
    operator makes it ACTIVE again the drone gets a session without the agent being restarted."""
    drone.until(True, Grant.AVAILABLE)
    assert "INACTIVE" in rig.event(kind="qod_profile", profile="QOS_E", status="INACTIVE")
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "QOS_E is INACTIVE" in told.reason
    assert "qos_profile" in told.reason
    rejected_before = rig.counters()["qod"]["rejected"]
    started = time.monotonic()
    while time.monotonic() - started < 2.5:  # more than two re-reads: still no create
        drone.until(True, Grant.UNAVAILABLE)
    assert rig.counters()["qod"]["created"] == 1
    assert rig.counters()["qod"]["rejected"] == rejected_before  # no create was tried while INACTIVE
    rig.event(kind="qod_profile", profile="QOS_E", status="ACTIVE")
    drone.until(True, Grant.AVAILABLE, timeout_s=5.0)
    assert rig.counters()["qod"]["created"] == 2
    log = rig.procs.pop("agent").stop()
    assert sum("no new sessions" in line for line in log.splitlines()) == 1, log[-3000:]
    assert "the operator's profile changed: profile QOS_E is ACTIVE" in log


@pytest.mark.parametrize("rig", [("camara", "", "profile_recheck_s = 3600\n")], indirect=True)
def test_camara_a_create_refused_for_a_withdrawn_profile_reads_the_profiles_again_at_once(
    rig: Rig, drone: Drone
) -> None:
    """The operator stops offering QOS_E between two sessions (no periodic re-read due): the next create
    is a 422 QOS_PROFILE_NOT_APPLICABLE, the agent reads the profiles again at once, finds it gone, and
    tells the drone so, without asking again."""
    drone.until(True, Grant.AVAILABLE)
    drone.until(False, Grant.NONE, also=lambda: rig.sessions() == [])
    rig.event(kind="qod_profile", profile="QOS_E", status="WITHDRAWN")
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "profile QOS_E is not offered" in told.reason
    started = time.monotonic()
    while time.monotonic() - started < 2.0:  # retry_after_denied_s is 0.5 s: a back-off would ask again
        drone.until(True, Grant.UNAVAILABLE)
    assert rig.counters()["qod"]["rejected"] == 1
    log = rig.procs.pop("agent").stop()
    assert "QOS_PROFILE_NOT_APPLICABLE" in log
    assert "the profile had changed" in log


@pytest.mark.parametrize(
    ("rig", "served"),
    [
        (("camara", 'qod_api_version = "1.2.0"\n', ADDRESSES), True),
        (("camara", "", ADDRESSES), False),
    ],
    indirect=["rig"],
    ids=["operator-1.2.0", "operator-1.1.0"],
)
def test_camara_the_edge_named_by_an_address_list_is_served_by_a_1_2_operator_and_refused_by_1_1(
    rig: Rig, drone: Drone, served: bool
) -> None:
    """QoD 1.2.0 names the application server by a list of single addresses (an edge router reachable
    at two addresses); an operator serving 1.1.0 answers that body 400, which is the agent's settings
    to fix: told once, not asked again."""
    if served:
        drone.until(True, Grant.AVAILABLE, also=rig.granted)
        (session,) = rig.sessions()
        assert session["applicationServer"] == {"ipAddresses": ["127.0.0.1", "127.0.0.2"]}
        return
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "INVALID_ARGUMENT" in told.reason
    assert "api_version" in told.reason
    started = time.monotonic()
    while time.monotonic() - started < 2.0:  # the drone keeps asking; retry_after_denied_s is 0.5 s
        drone.until(True, Grant.UNAVAILABLE)
    assert rig.counters()["qod"]["rejected"] == 1  # one create, not asked again
    assert rig.counters()["qod"]["created"] == 0


@pytest.mark.parametrize("mode", ["client-secret", "private-key-jwt", "three-legged"])
def test_camara_each_oauth2_mode_flies_a_drone_to_priority_against_the_real_cell(
    tmp_path: Path, mode: str
) -> None:
    """The agent gets its tokens from the emulated operator's token endpoint with a client secret, with a
    signed client assertion (RFC 7523) checked against the registered public key, or (three-legged) per
    drone by the JWT-bearer grant with its tel: login hint and no `device` in any body; in each mode the
    drone gets its session."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import rsa

    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    key_file = tmp_path / "agent.pem"
    key_file.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))  # fmt: skip
    secret_file = tmp_path / "secret"
    secret_file.write_text("s3cret\n")
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    config = tmp_path / "qos.toml"
    credential = (
        f'client_secret_file = "{secret_file}"'
        if mode == "client-secret"
        else f'client_key_file = "{key_file}"'
    )
    camara = (f'token_url = "http://127.0.0.1:{cell_port}/oauth2/token"\nclient_id = "dynqos-edge"\n'
              f'{credential}\nthree_legged = {str(mode == "three-legged").lower()}\n')  # fmt: skip
    write_config(config, zcfg, cell_port, "camara", "qod_auth = true\n", camara)
    with running(config, zcfg, cell_port) as rig:
        drone = Drone(zcfg)
        try:
            granted = drone.until(True, Grant.AVAILABLE, also=rig.granted)
            assert granted.session_id
        finally:
            drone.close()
        log = rig.procs.pop("agent").stop()
    assert "operator: new access token" in log
    assert ("for tel:+46700000001" in log) == (mode == "three-legged")  # whose token it was


def test_camara_fixed_api_key_headers_fly_a_drone_to_priority_against_the_real_cell(tmp_path: Path) -> None:
    headers = tmp_path / "qod-headers"
    headers.write_text("X-API-Key: k3y\n")
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    config = tmp_path / "qos.toml"
    write_config(config, zcfg, cell_port, "camara", "qod_auth = true\n", f'headers_file = "{headers}"\n')
    with running(config, zcfg, cell_port) as rig:
        drone = Drone(zcfg)
        try:
            assert drone.until(True, Grant.AVAILABLE, also=rig.granted).session_id
        finally:
            drone.close()


@pytest.mark.parametrize("rig", [("links", "")], indirect=True)
def test_links_priority_is_available_at_once_and_the_network_is_not_asked(rig: Rig, drone: Drone) -> None:
    granted = drone.until(True, Grant.AVAILABLE)
    assert (granted.backend, granted.session_id) == ("links", "")
    drone.until(False, Grant.NONE)
    assert rig.counters()["qod"]["created"] == 0


@contextlib.contextmanager
def agent_for(
    operator_root: str, tmp_path: Path, camara: str = "", zcfg: ZenohConfig | None = None
) -> Iterator[tuple[list[DynqosProcess], Drone]]:
    """The router and the QoS agent (backend camara, uav1's device) in front of a scripted operator, and a
    test drone; every process stopped by its pid after (their stderr in `stopped_stderr`)."""
    zcfg = zcfg or ZenohConfig(**flow_ports())
    config = tmp_path / "qos.toml"
    config.write_text(
        f"[zenoh]\ndefault_port = {zcfg.default_port}\npriority_port = {zcfg.priority_port}\n"
        f'[qos]\nbackend = "camara"\ngrant_interval_s = 0.2\n[qos.camara]\napi_root = "{operator_root}"\n'
        f'{camara}[qos.camara.devices]\n{UAV} = {{ phoneNumber = "+46700000001" }}\n'
    )
    procs = [DynqosProcess(["edge", "router"], config)]
    drone = None
    stopped_stderr.clear()
    try:
        procs.append(DynqosProcess(["edge", "qos"], config))
        drone = Drone(zcfg)
        yield procs, drone
    finally:
        if drone is not None:
            drone.close()
        stopped_stderr.extend(proc.stop() for proc in reversed(procs))


stopped_stderr: list[str] = []


class ScriptedOperator:
    """A scripted QoD operator: http.server on 127.0.0.1 in a thread, answering as its subclass says."""

    def _serve(self, handler: type[http.server.BaseHTTPRequestHandler]) -> None:
        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    @property
    def root(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/qod"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


class QuietHandler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *_: object) -> None:
        pass

    def _answer(self, status: int, body: Any = None) -> None:
        data = b"" if body is None else json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)


class SlowOperator(ScriptedOperator):
    """A scripted QoD operator (http.server on 127.0.0.1, in a thread) whose create answers only after
    `delay_s`: what a real one may do, and what the emulated cell never does."""

    SESSION_ID = "6f0d8f5e-1c7c-4d5b-9b1e-2a9d7c3e4f50"

    def __init__(self, port: int, delay_s: float) -> None:
        self.created = threading.Event()
        self.create_seen = threading.Event()
        self.calls: list[str] = []
        self.port = port
        operator = self

        class Handler(QuietHandler):
            def _session(self, status: str) -> dict[str, Any]:
                return {
                    "sessionId": operator.SESSION_ID, "duration": 60, "qosStatus": status,
                    "applicationServer": {"ipv4Address": "127.0.0.1"}, "qosProfile": "QOS_E",
                    "applicationServerPorts": {"ports": [operator.port]},
                }  # fmt: skip

            def do_POST(self) -> None:
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                operator.calls.append(f"POST {self.path}")
                if self.path.endswith("/retrieve-sessions"):
                    alive = (
                        operator.created.is_set()
                        and f"DELETE /qod/sessions/{operator.SESSION_ID}" not in operator.calls
                    )
                    self._answer(200, [self._session("AVAILABLE")] if alive else [])
                    return
                operator.create_seen.set()
                time.sleep(delay_s)  # the slow operator, on its own handler thread
                operator.created.set()
                self._answer(201, self._session("REQUESTED"))

            def do_GET(self) -> None:
                operator.calls.append(f"GET {self.path}")
                self._answer(200, self._session("AVAILABLE"))

            def do_DELETE(self) -> None:
                operator.calls.append(f"DELETE {self.path}")
                self._answer(204)

        self._serve(Handler)


def test_camara_a_create_in_flight_at_sigterm_is_waited_for_and_its_session_deleted(tmp_path: Path) -> None:
    zcfg = ZenohConfig(**flow_ports())
    operator = SlowOperator(zcfg.priority_port, delay_s=1.0)  # its sessions name the agent's port
    try:
        with agent_for(operator.root, tmp_path, "timeout_s = 3.0\n", zcfg) as (procs, drone):
            drone.ask(True)
            assert operator.create_seen.wait(15), "the agent never asked the operator"
            procs[1].proc.send_signal(signal.SIGTERM)  # while the create is still unanswered
            assert procs[1].proc.wait(timeout=20) == 0
            assert operator.created.is_set()
            assert f"DELETE /qod/sessions/{SlowOperator.SESSION_ID}" in operator.calls, operator.calls
    finally:
        operator.close()


class RefusingOperator(ScriptedOperator):
    """A scripted operator (http.server on 127.0.0.1) that answers every create with one CAMARA error
    and counts the calls: what a real operator says to settings it will not take."""

    def __init__(self, status: int, code: str) -> None:
        self.calls: list[str] = []
        operator = self

        class Handler(QuietHandler):
            def do_POST(self) -> None:
                self.rfile.read(int(self.headers.get("Content-Length", 0)))
                operator.calls.append(f"POST {self.path} {self.headers.get('x-correlator', '')}")
                body: Any = [] if self.path.endswith("/retrieve-sessions") else {
                    "status": status, "code": code, "message": "as the spec says"
                }  # fmt: skip
                self._answer(200 if isinstance(body, list) else status, body)

        self._serve(Handler)

    def creates(self) -> list[str]:
        return [c for c in self.calls if c.startswith("POST /qod/sessions ")]


@pytest.mark.parametrize(
    ("status", "code", "setting"),
    [
        (422, "UNNECESSARY_IDENTIFIER", "[qos.camara.devices]"),
        (400, "QUALITY_ON_DEMAND.DURATION_OUT_OF_RANGE", "duration_s"),
        (403, "PERMISSION_DENIED", "scopes"),
        (400, "INVALID_ARGUMENT", "api_version"),
    ],
)
def test_camara_settings_the_operator_refuses_are_one_error_line_and_no_retry_storm(
    tmp_path: Path, status: int, code: str, setting: str
) -> None:
    operator = RefusingOperator(status, code)
    try:
        with agent_for(operator.root, tmp_path, "retry_after_denied_s = 0.1\n") as (_, drone):
            told = drone.until(True, Grant.UNAVAILABLE)
            assert code in told.reason
            assert setting in told.reason
            assert "x-correlator" in told.reason
            started = time.monotonic()
            while time.monotonic() - started < 3.0:  # the drone keeps asking, as it does in flight
                drone.until(True, Grant.UNAVAILABLE)
            assert len(operator.creates()) == 1, operator.calls  # the back-off alone asked ~20 times
    finally:
        operator.close()
    refused = [line for line in "".join(stopped_stderr).splitlines() if "refused our settings" in line]
    assert len(refused) == 1, "".join(stopped_stderr)[-2000:]
    assert setting in refused[0]


@pytest.mark.parametrize("mode", ["wrong-secret", "foreign-key"])
def test_camara_credentials_the_token_endpoint_refuses_stop_the_agent_before_it_serves(
    tmp_path: Path, mode: str
) -> None:
    """A client secret or a signing key the operator does not know: the agent's first call (the profile
    read) is refused a token; the agent says so in one line naming the setting and exits 2, having asked
    for one token, instead of serving drones that could only be refused."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import rsa

    pem = {}
    for who in ("registered", "agent"):
        key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
        pem[who] = tmp_path / f"{who}.pem"
        pem[who].write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                               serialization.NoEncryption()))  # fmt: skip
    (tmp_path / "secret").write_text("s3cret\n")
    (tmp_path / "guess").write_text("guessed\n")
    zcfg = ZenohConfig(**flow_ports())
    cell_port = free_tcp_port()
    token = f'token_url = "http://127.0.0.1:{cell_port}/oauth2/token"\nclient_id = "dynqos-edge"\n'
    credential = {"cell": "secret", "agent": "guess"} if mode == "wrong-secret" else None
    for who in ("cell", "agent"):
        if credential is not None:
            line = f'client_secret_file = "{tmp_path / credential[who]}"\n'
        else:
            line = f'client_key_file = "{pem["registered" if who == "cell" else "agent"]}"\n'
        write_config(tmp_path / f"{who}.toml", zcfg, cell_port, "camara", "qod_auth = true\n", token + line)
    procs: dict[str, DynqosProcess] = {}
    try:
        procs["router"] = DynqosProcess(["edge", "router"], tmp_path / "cell.toml")
        procs["cell"] = DynqosProcess(["sim", "cell"], tmp_path / "cell.toml")
        error = refused_at_start(tmp_path / "agent.toml", "qos.camara.client_id")
        assert "client_secret_file, client_key_file" in error
        qod = Rig(tmp_path / "cell.toml", zcfg, cell_port, procs).counters()["qod"]
        assert (qod["tokens_refused"], qod["tokens_issued"]) == (1, 0)
    finally:
        for proc in reversed(list(procs.values())):
            proc.stop()
