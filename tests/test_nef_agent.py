"""`dynqos edge qos` with `backend = "nef"`: the agent asks a 5G core's NEF (AsSessionWithQoS) for the
drone's priority flow. Real processes on 127.0.0.1: the router, the emulated cell serving its NEF
(`[cell] nef = true`) and the agent, with a test drone asking over zenoh; and the rules that map the
NEF's notifications onto the drone's grant, in-process with the time passed in."""

from __future__ import annotations

import asyncio
import itertools
import json
import signal
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dynqos.common import keys
from dynqos.common.bus import Received
from dynqos.common.clock import FakeClock
from dynqos.common.config import CamaraConfig, CellConfig, QosConfig, ZenohConfig
from dynqos.common.config.nef import NefConfig, NefUeConfig
from dynqos.common.keys import Downlink
from dynqos.common.messages import QosMonitoring
from dynqos.common.modes import Grant
from dynqos.common.queues import BoundedQueue
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.nef import API, FlowRule, Report, Subscription
from dynqos.edge.qos.grants import DroneGrant, Op, QodStatus, Session
from dynqos.edge.qos.nef_calls import NefCalls
from dynqos.edge.qos.nef_sink import NefSinkGuard
from tests.conftest import flow_ports, free_tcp_port
from tests.procs import DynqosProcess, start_together
from tests.test_qos_agent import UAV, Drone
from tests.test_qos_standby import actives

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

UE = "10.45.0.7"


class NefRig:
    """The router, the cell with its NEF, and the agent (backend nef); each stopped by its pid after."""

    def __init__(
        self, tmp_path: Path, nef: str = "", ue: str = UE, cell: str = "", tail: str = "", cell_port: int = 0
    ) -> None:
        self.zenoh = ZenohConfig(**flow_ports())
        self.cell_port = cell_port or free_tcp_port()
        self.sink_port = free_tcp_port()
        self.config = tmp_path / "qos.toml"
        z = self.zenoh
        self.config.write_text(
            f"[zenoh]\ndefault_port = {z.default_port}\npriority_port = {z.priority_port}\n"
            f"[cell]\nqod = true\nnef = true\ncontrol_port = {self.cell_port}\ndefault_listen_port = 0\n"
            f"priority_listen_port = 0\nqod_setup_s = 0.1\n{cell}"
            '[qos]\nbackend = "nef"\nhold_down_s = 0.5\ngrant_interval_s = 0.2\nagent_timeout_s = 1.0\n'
            "drone_timeout_s = 2.0\nrequest_interval_s = 0.2\nhealth_interval_s = 1.0\n"
            f'[qos.nef]\napi_root = "http://127.0.0.1:{self.cell_port}"\n'
            f'notification_destination = "http://127.0.0.1:{self.sink_port}/nef-events"\n'
            f'sink_listen = "127.0.0.1:{self.sink_port}"\nread_interval_s = 1.0\nretry_after_denied_s = 0.5\n'
            f"{nef}"
            f'[qos.nef.ues]\n{UAV} = {{ ipv4 = "{ue}" }}\n'
            # the core's own UE records (the emulated cell reads the drones' devices from here)
            f"[qos.camara.devices.{UAV}]\n"
            f'ipv4Address = {{ publicAddress = "203.0.113.7", privateAddress = "{UE}" }}\n{tail}'
        )
        self.procs: dict[str, DynqosProcess] = {}
        self.procs["router"], self.procs["cell"] = start_together(
            self.config, ["edge", "router"], ["sim", "cell"]
        )
        self.procs["agent"] = DynqosProcess(["edge", "qos"], self.config)

    def close(self) -> str:
        return "".join(proc.stop() for proc in reversed(list(self.procs.values())))

    def _get(self, path: str) -> Any:
        with urllib.request.urlopen(f"http://127.0.0.1:{self.cell_port}{path}", timeout=5) as r:
            return json.loads(r.read())

    def nef(self) -> dict[str, int]:
        counters: dict[str, int] = self._get("/counters")["nef"]
        return counters

    def subscriptions(self) -> list[dict[str, Any]]:
        found: list[dict[str, Any]] = self._get(f"{API}/dynqos/subscriptions")
        return found

    def granted(self) -> bool:
        return bool(self._get("/counters")["bearers"][f"{UAV}-priority"]["granted"])

    def event(self, **event: Any) -> None:
        request = urllib.request.Request(
            f"http://127.0.0.1:{self.cell_port}/events",
            json.dumps(event).encode(),
            headers={"Content-Type": "application/json"},
        )
        urllib.request.urlopen(request, timeout=5).close()


@pytest.fixture
def rig(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[NefRig]:
    started = NefRig(tmp_path, *getattr(request, "param", ()))
    try:
        yield started
    finally:
        started.close()


@pytest.fixture
def drone(rig: NefRig) -> Iterator[Drone]:
    d = Drone(rig.zenoh)
    try:
        yield d
    finally:
        d.close()


def test_nef_a_drone_gets_a_subscription_while_it_wants_priority_and_none_after(
    rig: NefRig, drone: Drone
) -> None:
    granted = drone.until(True, Grant.AVAILABLE, also=rig.granted)
    assert granted.backend == "nef"
    (sub,) = rig.subscriptions()
    assert sub["self"].endswith(f"/subscriptions/{granted.session_id}")
    assert sub["ueIpv4Addr"] == UE
    assert sub["qosReference"] == "QOS_E"
    rules = sub["flowInfo"][0]["flowDescriptions"]
    assert rules == [
        f"permit out 6 from {UE} to 127.0.0.1 {rig.zenoh.priority_port}",
        f"permit out 6 from 127.0.0.1 {rig.zenoh.priority_port} to {UE}",
    ]
    destination = sub["notificationDestination"]
    assert destination.startswith(f"http://127.0.0.1:{rig.sink_port}/nef-events/")
    assert len(destination.rsplit("/", 1)[1]) >= 40  # the agent's secret segment
    drone.until(False, Grant.NONE, also=lambda: rig.subscriptions() == [])  # after the hold-down
    assert not rig.granted()
    counters = rig.nef()
    assert (counters["created"], counters["deleted"], counters["rejected"]) == (1, 1, 0)


def test_nef_the_network_ending_a_subscription_is_told_and_asked_again(rig: NefRig, drone: Drone) -> None:
    first = drone.until(True, Grant.AVAILABLE)
    rig.event(kind="qod_end", uav=UAV)
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "SESSION_TERMINATION" in told.reason
    again = drone.until(True, Grant.AVAILABLE, also=rig.granted)  # after the back-off, a new one
    assert again.session_id != first.session_id
    assert [s["self"].rsplit("/", 1)[1] for s in rig.subscriptions()] == [again.session_id]
    assert rig.nef()["terminated"] == 1


def test_nef_sigterm_deletes_the_subscription_and_a_forged_notification_changes_nothing(
    rig: NefRig, drone: Drone
) -> None:
    granted = drone.until(True, Grant.AVAILABLE)
    (sub,) = rig.subscriptions()
    forged = {"transaction": sub["self"], "eventReports": [{"event": "SESSION_TERMINATION"}]}
    wrong_path = f"http://127.0.0.1:{rig.sink_port}/nef-events/not-the-agents-secret"
    request = urllib.request.Request(
        wrong_path, json.dumps(forged).encode(), headers={"Content-Type": "application/json"}
    )
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=5)
    refused.value.close()
    assert refused.value.code == 401
    still = drone.until(True, Grant.AVAILABLE)  # the grant did not move
    assert still.session_id == granted.session_id
    agent = rig.procs["agent"]
    agent.proc.send_signal(signal.SIGTERM)
    assert agent.proc.wait(timeout=20) == 0
    assert rig.subscriptions() == []
    err = agent.stop()
    assert "deleted (stopping)" in err
    assert "refused a NEF notification" in err


def test_nef_a_standby_adopts_the_subscription_of_an_agent_that_died_and_hears_its_events(
    rig: NefRig, drone: Drone
) -> None:
    first = drone.until(True, Grant.AVAILABLE)
    port = free_tcp_port()  # a standby on this host listens for its notifications on a port of its own
    rig.procs["standby"] = DynqosProcess(
        [
            "edge",
            "qos",
            "--set",
            f'qos.nef.sink_listen="127.0.0.1:{port}"',
            "--set",
            f'qos.nef.notification_destination="http://127.0.0.1:{port}/nef-events"',
        ],
        rig.config,
    )
    assert len(actives(rig.zenoh)) == 1  # the first agent stays active while it lives
    drone.until(True, Grant.AVAILABLE)  # the standby has heard the drone just now
    dead = rig.procs.pop("agent")
    dead.proc.kill()  # a crash: no clean-up, the subscription stays
    dead.proc.wait(timeout=10)
    dead.stop()
    again = drone.until(True, Grant.AVAILABLE, also=lambda: rig.nef()["modified"] >= 1)
    assert again.session_id == first.session_id  # adopted, not created again
    assert rig.nef()["created"] == 1
    (sub,) = rig.subscriptions()
    assert sub["notificationDestination"].startswith(f"http://127.0.0.1:{port}/nef-events/")
    rig.event(kind="qod_end", uav=UAV)  # its notifications now reach the standby's sink
    told = drone.until(True, Grant.UNAVAILABLE)
    assert "SESSION_TERMINATION" in told.reason


@pytest.mark.parametrize("rig", [("qos_monitoring = true\nmonitoring_period_s = 1\n",)], indirect=True)
def test_nef_the_cores_delay_reports_reach_the_drone_at_the_period_asked_for(
    rig: NefRig, drone: Drone
) -> None:
    reports: BoundedQueue[Received] = BoundedQueue(100)
    drone.bus.subscribe(keys.downlink(UAV, Downlink.QOS_MONITORING), reports, expect=(QosMonitoring,))
    granted = drone.until(True, Grant.AVAILABLE)
    (sub,) = rig.subscriptions()
    assert sub["qosMonInfo"]["repPeriod"] == 1
    heard: list[Received] = []
    deadline = time.monotonic() + 4.5
    while time.monotonic() < deadline:
        drone.ask(True)  # as the drone keeps asking in flight
        item = reports.get(0.2)
        heard += [item] if item is not None else []
    assert 3 <= len(heard) <= 6, [r.arrival_ns for r in heard]
    gaps_s = [(b.arrival_ns - a.arrival_ns) / 1e9 for a, b in itertools.pairwise(heard)]
    assert all(0.6 <= gap <= 1.5 for gap in gaps_s), gaps_s  # one a period, as asked
    for item in heard:
        message = item.message
        assert isinstance(message, QosMonitoring)
        assert (message.uav, message.subscription_id, message.period_s) == (UAV, granted.session_id, 1)
        assert message.round_trip_ms is not None
        assert message.round_trip_ms >= 2 * CellConfig().base_delay_up_ms  # the cell's delays, both ways
    assert rig.nef()["reports"] >= len(heard)
    drone.until(False, Grant.NONE, also=lambda: rig.subscriptions() == [])
    while reports.get(1.5) is not None:  # one may have been on its way
        pass
    assert reports.get(1.5) is None  # no subscription, no report


@pytest.mark.parametrize(
    ("rig", "setting", "refusals"),
    [
        (('qos_reference = "QOS_NOT_OFFERED"\n',), "qos_reference", 1),
        (("", "10.45.0.99"), "ues", 1),
        # the NEF serves another SCS/AS: the read at start is refused too (one warning), then the create
        (('scs_as_id = "nobody"\n', UE, 'nef_scs_as_ids = ["dynqos"]\n'), "scs_as_id", 2),
    ],
    indirect=["rig"],
    ids=["unknown-reference", "unknown-ue", "unknown-scs-as"],
)
def test_nef_settings_the_nef_refuses_are_one_error_line_and_no_retry_storm(
    rig: NefRig, drone: Drone, setting: str, refusals: int
) -> None:
    told = drone.until(True, Grant.UNAVAILABLE)
    assert setting in told.reason
    started = time.monotonic()
    while time.monotonic() - started < 3.0:  # the drone keeps asking, as it does in flight
        drone.until(True, Grant.UNAVAILABLE)
    assert rig.nef()["rejected"] == refusals  # the back-off alone (0.5 s) would have asked ~5 times
    assert rig.nef()["created"] == 0
    refused = [line for line in rig.close().splitlines() if "refused our settings" in line]
    assert len(refused) == 1
    assert setting in refused[0]


def test_nef_credentials_the_token_endpoint_refuses_are_one_error_line_and_no_retry_storm(
    tmp_path: Path,
) -> None:
    """[qos.nef] token_url with a secret the authorisation server does not know (the emulated cell's
    token endpoint, which knows another): the drone is told why, the agent says so once and asks again
    only when restarted."""
    (tmp_path / "secret").write_text("s3cret\n")
    (tmp_path / "guess").write_text("guessed\n")
    token = f'client_id = "dynqos-edge"\nclient_secret_file = "{tmp_path / "guess"}"\n'
    registered = f'[qos.camara]\nclient_id = "dynqos-edge"\nclient_secret_file = "{tmp_path / "secret"}"\n'
    port = free_tcp_port()
    nef = f'token_url = "http://127.0.0.1:{port}/oauth2/token"\n{token}'
    rig = NefRig(tmp_path, nef, cell="qod_auth = true\n", tail=registered, cell_port=port)
    try:
        drone = Drone(rig.zenoh)
        try:
            told = drone.until(True, Grant.UNAVAILABLE)
            assert "client_id" in told.reason
            started = time.monotonic()
            while time.monotonic() - started < 3.0:  # the drone keeps asking, as it does in flight
                drone.until(True, Grant.UNAVAILABLE)
        finally:
            drone.close()
        counters = rig._get("/counters")
        # asked twice: the read for subscriptions to adopt at start, and the one create; the back-off
        # alone would have asked ~5 times more
        assert counters["qod"]["tokens_refused"] == 2
        assert counters["nef"]["created"] == 0
    finally:
        log = rig.close()
    refused = [line for line in log.splitlines() if "refused our settings" in line]
    assert len(refused) == 1
    assert "client_id" in refused[0]
    assert "Traceback" not in log


# ---- the rules, in-process --------------------------------------------------------------------------


def _calls(clock: FakeClock, duration_s: int = 0) -> tuple[NefCalls, DroneGrant]:
    nef = NefConfig(
        api_root="http://127.0.0.1:9",
        notification_destination="http://127.0.0.1:9/n",
        sink_listen="127.0.0.1:9",
        qos_duration_s=duration_s,
        ues={UAV: NefUeConfig(ipv4=UE)},
    )
    config = QosConfig(backend="nef", nef=nef)
    operator = OperatorClient(CamaraConfig())  # never opened: no call is made here
    calls = NefCalls(operator, nef, 7447, "127.0.0.1", clock, NefSinkGuard())
    return calls, DroneGrant(UAV, config, clock.now_ns())


def test_nef_events_move_the_grant_as_qod_statuses_do() -> None:
    clock = FakeClock()
    calls, grant = _calls(clock)
    grant.request(True, 1, clock.now_ns())
    assert grant.next_op(clock.now_ns()) is Op.CREATE
    grant.observed(Session("s1", QodStatus.REQUESTED), clock.now_ns())
    assert grant.grant(clock.now_ns()) is Grant.REQUESTED
    assert calls.notified([Report("s1", "QOS_GUARANTEED")], [grant]) == [grant]
    assert grant.grant(clock.now_ns()) is Grant.AVAILABLE
    clock.advance_s(30)  # no end to extend: only reads come due
    grant.request(True, 2, clock.now_ns())
    assert grant.next_op(clock.now_ns()) is Op.POLL
    calls.notified([Report("s1", "QOS_NOT_GUARANTEED")], [grant])
    assert grant.grant(clock.now_ns()) is Grant.REQUESTED
    calls.notified([Report("s1", "QOS_MONITORING", (12,), (8,), (20,))], [grant])
    assert calls.monitoring[UAV].round_trip_ms == (20,)
    assert grant.grant(clock.now_ns()) is Grant.REQUESTED  # a report is no state
    calls.notified([Report("s1", "QOS_GUARANTEED"), Report("s1", "SESSION_TERMINATION")], [grant])
    assert grant.grant(clock.now_ns()) is Grant.UNAVAILABLE
    assert "SESSION_TERMINATION" in grant.why()
    assert grant.next_op(clock.now_ns()) is Op.DELETE


def test_nef_an_event_before_the_create_answers_is_kept_for_it_and_others_are_unknown() -> None:
    clock = FakeClock()
    calls, grant = _calls(clock)
    assert calls.notified([Report("early", "QOS_GUARANTEED")], [grant]) == []
    assert calls.unknown == 1
    assert calls._early["early"] == (QodStatus.AVAILABLE, "")  # taken by the create that answers "early"


def test_nef_a_subscription_that_ran_its_duration_is_asked_for_again_at_once() -> None:
    clock = FakeClock()
    calls, grant = _calls(clock, duration_s=60)
    grant.request(True, 1, clock.now_ns())
    calls._created_ns["s1"] = clock.now_ns()
    grant.observed(Session("s1", QodStatus.AVAILABLE), clock.now_ns())
    clock.advance_s(60)
    grant.request(True, 2, clock.now_ns())
    calls.notified([Report("s1", "SESSION_TERMINATION")], [grant])
    assert grant.session is not None
    assert grant.session.status_info == "DURATION_EXPIRED"
    assert grant.next_op(clock.now_ns()) is Op.DELETE
    grant.deleted(clock.now_ns())
    assert grant.next_op(clock.now_ns()) is Op.CREATE  # no back-off


def test_nef_a_core_without_patch_has_an_adopted_subscription_deleted_not_left_behind() -> None:
    """A NEF that serves no PATCH (405) cannot point a dead agent's subscription at the new agent's sink:
    the new agent deletes it, and the drone, holding nothing, asks anew. Another error leaves it alone."""
    calls, _ = _calls(FakeClock())
    rules = FlowRule(UE, "127.0.0.1", 7447).descriptions()
    flows = [{"flowId": 1, "flowDescriptions": list(rules)}]
    body = {"self": "http://nef/x/subscriptions/s1", "ueIpv4Addr": UE, "qosReference": "QOS_E",
            "notificationDestination": "http://old", "flowInfo": flows}  # fmt: skip
    deleted: list[str] = []

    class NoPatch:
        status = 405

        async def all(self) -> list[Subscription]:
            return [Subscription.parse(body)]

        async def modify(self, sid: str, changes: dict[str, Any]) -> Subscription:
            raise OperatorError(self.status, "METHOD_NOT_ALLOWED", "no PATCH here")

        async def delete(self, sid: str) -> None:
            deleted.append(sid)

    api = NoPatch()
    calls.api = api  # type: ignore[assignment]
    assert asyncio.run(calls.adopt({UAV})) == {}
    assert deleted == ["s1"]
    api.status = 503  # the NEF's trouble, not a missing method: neither adopted nor deleted
    assert asyncio.run(calls.adopt({UAV})) == {}
    assert deleted == ["s1"]
