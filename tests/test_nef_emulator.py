"""The emulated NEF (sim/network/nef.py) as pure logic on a fake clock: what it allocates, refuses, ends
and reports, what it answers (checked against TS 29.122's own document where ../shared/3gpp has it), and
that dynqos's own NEF client's requests are what it takes."""

from __future__ import annotations

from typing import Any

import pytest

from dynqos.common.config import CellConfig
from dynqos.edge.operator.nef import FlowRule, Monitoring, SubscriptionRequest
from dynqos.sim.network.nef import API, Nef, parse_rule
from tests import nef_spec

UE, EDGE, PORT = "10.45.0.7", "192.0.2.10", 7448
DEVICES = {"uav1": {"phoneNumber": "+34600000001", "ipv4Address": {"privateAddress": UE}}}


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def nef(**cell: Any) -> tuple[Nef, Clock]:
    clock = Clock()
    settings = {"qod_setup_s": 0.5} | cell
    return Nef(CellConfig(**settings), DEVICES, {"uav1": EDGE}, clock, root="http://nef"), clock


def request(**changes: Any) -> dict[str, Any]:
    ask = SubscriptionRequest(
        ue_ipv4=UE,
        flows=(FlowRule(UE, EDGE, PORT),),
        qos_reference="QOS_E",
        notification_destination="http://127.0.0.1:9/nef",
        monitoring=Monitoring(period_s=2),
    )
    return ask.body() | changes


def measured(_uav: str) -> tuple[int, int, int]:
    return (4, 5, 9)


def test_an_ipfilterrule_gives_its_two_ends_and_their_ports() -> None:
    rule = parse_rule(f"permit out 6 from {UE} to {EDGE} 7447-7448,9000")
    assert (rule.source, rule.destination) == (UE, EDGE)
    assert rule.source_ports == frozenset()
    assert rule.destination_ports == {7447, 7448, 9000}
    bad = (
        "deny out 6 from any to any",
        "permit out 6 from host to any",
        "permit out 6 to x from y",
        f"permit out tcp from {UE} to {EDGE} 1",
        f"permit out 6 from {UE} to {EDGE} 9-1",
    )
    for text in bad:
        with pytest.raises(ValueError, match=r"IPFilterRule|protocol|network|ports"):
            parse_rule(text)


def test_a_subscription_is_allocated_after_the_setup_time_and_grants_only_its_flow() -> None:
    core, clock = nef()
    answer, notes = core.create("edge-a", request())
    assert answer.status == 201
    assert notes == []
    assert answer.body["self"].startswith(f"http://nef{API}/edge-a/subscriptions/")
    assert not core.granted("uav1", PORT)  # still being set up
    clock.now += 0.5
    notes = core.advance(measured)
    assert [e["event"] for n in notes for e in n.event["eventReports"]] == [
        "SUCCESSFUL_RESOURCES_ALLOCATION",
        "QOS_GUARANTEED",
    ]
    assert notes[0].content_type == "application/json"
    assert notes[0].event["transaction"] == answer.body["self"]
    assert core.granted("uav1", PORT)
    assert not core.granted("uav1", 7447)  # the default flow's port is not in its rules
    assert not core.granted("uav2", PORT)


def test_monitoring_reports_come_every_period_with_the_flows_delays() -> None:
    core, clock = nef()
    core.create("edge-a", request())
    clock.now += 0.5
    core.advance(measured)
    clock.now += 1.9
    assert core.advance(measured) == []  # the period is 2 s
    clock.now += 0.1
    assert core.advance() == []  # a read through the API settles; only the cell's clock reports
    (note,) = core.advance(lambda uav: (11, 12, 23))
    (report,) = note.event["eventReports"]
    assert report["event"] == "QOS_MONITORING"
    assert report["qosMonReports"] == [{"ulDelays": [11], "dlDelays": [12], "rtDelays": [23]}]


def test_the_admission_limit_refuses_and_the_network_ends_and_qos_duration_expires() -> None:
    core, clock = nef(qod_max_sessions=0)
    core.create("edge-a", request())
    clock.now += 0.5
    (note,) = core.advance(measured)
    assert note.event["eventReports"] == [{"event": "FAILED_RESOURCES_ALLOCATION"}]
    assert not core.granted("uav1", PORT)

    core, clock = nef()
    core.create("edge-a", request(qosDuration=10))
    clock.now += 0.5
    core.advance(measured)
    (ended,) = core.end("uav1")
    assert ended.event["eventReports"] == [{"event": "SESSION_TERMINATION"}]
    assert not core.granted("uav1", PORT)
    core.create("edge-a", request(qosDuration=10))
    clock.now += 0.5
    core.advance(measured)
    clock.now += 10
    assert any(
        e["event"] == "SESSION_TERMINATION" for n in core.advance(measured) for e in n.event["eventReports"]
    )
    assert core.counters.expired == 1


def test_what_it_refuses_and_why() -> None:
    core, _ = nef()
    cases = {
        "no sink": (request(notificationDestination=""), 400),
        "two identities": (request(gpsi="msisdn-34600000001"), 400),
        "unknown UE": (request(ueIpv4Addr="10.45.0.99"), 404),
        "a rule to another host": (
            request(
                flowInfo=[
                    {"flowId": 1, "flowDescriptions": [f"permit out 6 from {UE} to 198.51.100.1 {PORT}"]}
                ]
            ),
            400,
        ),
        "a reference not offered": (request(qosReference="GOLD"), 403),
        "self given": (request(self="http://x"), 400),
    }
    for name, (body, status) in cases.items():
        answer, notes = core.create("edge-a", body)
        assert (answer.status, notes) == (status, []), name
        assert answer.body["cause"], name
        assert answer.body["detail"], name
    assert core.subscriptions == {}
    by_gpsi, _ = core.create("edge-a", request(ueIpv4Addr=None) | {"gpsi": "msisdn-34600000001"})
    assert by_gpsi.status == 201


def test_read_patch_and_delete_are_each_scs_as_s_own() -> None:
    core, clock = nef()
    created, _ = core.create("edge-a", request())
    sid = created.body["self"].rsplit("/", 1)[-1]
    assert core.get("edge-b", sid).status == 404  # another SCS/AS's does not exist for it
    assert core.all("edge-b").body == []
    assert [s["self"] for s in core.all("edge-a").body] == [created.body["self"]]
    patched = core.modify("edge-a", sid, {"qosReference": "QOS_L", "qosMonInfo": None})
    assert patched.status == 200
    assert patched.body["qosReference"] == "QOS_L"
    assert "qosMonInfo" not in patched.body
    assert core.modify("edge-a", sid, {"ueIpv4Addr": "10.45.0.8"}).status == 400  # not patchable
    clock.now += 5
    core.advance(measured)
    assert core.granted("uav1", PORT)
    assert core.delete("edge-b", sid).status == 404
    assert core.delete("edge-a", sid).status == 204
    assert not core.granted("uav1", PORT)
    assert core.get("edge-a", sid).status == 404


@pytest.mark.skipif(bool(nef_spec.available()), reason=nef_spec.available() or "")
def test_its_answers_are_what_the_document_describes() -> None:
    core, clock = nef()
    path = f"{API}/edge-a/subscriptions"
    created, _ = core.create("edge-a", request())
    sid = created.body["self"].rsplit("/", 1)[-1]
    clock.now += 0.5
    notes = core.advance(measured)
    assert created.location == created.body["self"]
    exchanges = [
        ("POST", path, request(), created.status, created.body, "application/json"),
        ("GET", f"{path}/{sid}", None, 200, core.get("edge-a", sid).body, "application/json"),
        ("GET", path, None, 200, core.all("edge-a").body, "application/json"),
        (
            "PATCH",
            f"{path}/{sid}",
            {"qosReference": "QOS_M"},
            200,
            core.modify("edge-a", sid, {"qosReference": "QOS_M"}).body,
            "application/merge-patch+json",
        ),
        ("GET", f"{path}/nope", None, 404, core.get("edge-a", "nope").body, "application/json"),
    ]
    found = [
        p
        for method, where, sent, status, answer, kind in exchanges
        for p in nef_spec.problems(
            method,
            where,
            sent,
            status,
            answer,
            content_type=kind,
            headers={"Location": created.location} if status == 201 else None,
        )
    ]
    assert found == []
    assert nef_spec.notification_problems(notes[0].event) == []


def test_a_put_replaces_the_subscription_but_not_its_ue_and_checks_it_as_a_creation() -> None:
    core, clock = nef()
    created, _ = core.create("edge-a", request())
    sid = created.body["self"].rsplit("/", 1)[-1]
    clock.now += 1
    core.advance(measured)
    new = request(qosReference="QOS_L")
    del new["qosMonInfo"]
    replaced = core.replace("edge-a", sid, new | {"self": "http://elsewhere/x"})
    assert replaced.status == 200
    assert replaced.body["self"] == created.body["self"]  # the NEF's, whatever was sent
    assert replaced.body["qosReference"] == "QOS_L"
    assert "qosMonInfo" not in core.get("edge-a", sid).body  # replaced, not merged
    assert core.granted("uav1", PORT)
    assert core.replace("edge-a", sid, request(ueIpv4Addr="10.45.0.99")).status == 400  # another UE
    assert core.replace("edge-a", sid, request(qosReference="")).status == 400
    assert core.replace("edge-a", sid, request(qosReference="QOS_X")).status == 403
    assert core.replace("edge-b", sid, request()).status == 404
    assert core.get("edge-a", sid).body["qosReference"] == "QOS_L"  # the refusals changed nothing


def test_a_read_of_all_names_ues_by_address_and_refuses_a_query_the_document_forbids() -> None:
    core, _ = nef()
    created, _ = core.create("edge-a", request())

    def read(ip_addrs: str | None = None, macs: list[str] | None = None) -> tuple[int, Any]:
        answer = core.all("edge-a", ip_addrs, macs)
        return answer.status, answer.body

    assert read(f'[{{"ipv4Addr": "{UE}"}}]') == (200, [created.body])
    assert read('[{"ipv4Addr": "10.45.0.8"}]') == (200, [])
    assert read('[{"ipv6Prefix": "2001:db8::/64"}]') == (200, [])
    assert read(macs=["aa-bb-cc-dd-ee-ff"]) == (200, [])
    for bad_ip in ("[]", "{", '[{"ipv4Addr": "1.2.3"}]', f'[{{"ipv4Addr": "{UE}", "ipv6Addr": "::1"}}]'):
        assert read(bad_ip)[0] == 400, bad_ip
    assert read(macs=["aa:bb:cc:dd:ee:ff"])[0] == 400
    assert read()[1] == [created.body]
