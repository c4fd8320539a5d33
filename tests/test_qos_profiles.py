"""Profiles first (edge/operator/profile_fit.py, profiles.py): the QoS Profiles API's answer decides
whether the agent may start and what duration it asks for; the emulated operator serves that API as
CAMARA qos-profiles v1.1.0 describes it."""

from __future__ import annotations

from typing import Any

import pytest

from dynqos.common.config import CamaraConfig, CellConfig
from dynqos.edge.operator.profile_fit import ProfileError, duration_s, fit
from dynqos.edge.operator.profiles import profiles_root
from dynqos.sim.network.operator import Operator


def profile(name: str, status: str = "ACTIVE", low: Any = None, high: Any = None) -> dict[str, Any]:
    out: dict[str, Any] = {"name": name, "status": status}
    if low is not None:
        out["minDuration"] = low
    if high is not None:
        out["maxDuration"] = high
    return out


def test_durations_in_every_camara_unit_and_malformed_ones() -> None:
    assert duration_s({"value": 2, "unit": "Hours"}) == 7200
    assert duration_s({"value": 1, "unit": "Days"}) == 86400
    assert duration_s({"value": 1500, "unit": "Milliseconds"}) == 1.5
    assert duration_s({"value": 3, "unit": "Fortnights"}) is None
    assert duration_s({"value": "3", "unit": "Seconds"}) is None
    assert duration_s({"value": True, "unit": "Seconds"}) is None
    assert duration_s(None) is None


def test_a_duration_inside_the_range_is_kept_and_one_outside_is_fitted() -> None:
    listed = [profile("QOS_S"), profile("QOS_E", low={"value": 10, "unit": "Seconds"},
                                        high={"value": 1, "unit": "Hours"})]  # fmt: skip
    assert fit(listed, "QOS_E", 600).duration_s == 600
    capped = fit(listed, "QOS_E", 86400)
    assert capped.duration_s == 3600
    assert "asking for 3600 s, not 86400" in capped.note
    assert fit(listed, "QOS_E", 4).duration_s == 10
    assert fit(listed, "QOS_S", 600).duration_s == 600  # no range given: nothing to fit


def test_a_profile_not_offered_or_not_active_is_refused_with_what_is_offered() -> None:
    listed = [profile("QOS_S"), profile("QOS_L"), profile("QOS_M", status="INACTIVE")]
    with pytest.raises(ProfileError, match=r"profile QOS_E is not offered \(offered: QOS_L, QOS_M, QOS_S\)"):
        fit(listed, "QOS_E", 600)
    with pytest.raises(ProfileError, match="QOS_M is INACTIVE"):
        fit(listed, "QOS_M", 600)
    with pytest.raises(ProfileError, match="QOS_D is DEPRECATED"):
        fit([profile("QOS_D", status="DEPRECATED")], "QOS_D", 600)
    with pytest.raises(ProfileError, match="did not answer a list"):
        fit({"code": "NOT_FOUND"}, "QOS_E", 600)


def test_the_profiles_api_lives_beside_the_qod_api_unless_set() -> None:
    camara = CamaraConfig(api_root="https://api.example/camara/quality-on-demand/v1/")
    assert profiles_root(camara) == "https://api.example/camara/qos-profiles/v1"
    own = CamaraConfig(api_root="https://a.example/qod", profiles_root="https://b.example/profiles/v1/")
    assert profiles_root(own) == "https://b.example/profiles/v1"


def operator(**cell: Any) -> Operator:
    config = CellConfig(qod=True, **cell)
    devices = {"uav1": {"phoneNumber": "+46700000001"}}
    return Operator(config, devices, {"uav1": "127.0.0.1"}, monotonic=lambda: 0.0, wall=lambda: 0.0)


def test_the_emulated_operator_lists_its_profiles_with_their_status_and_duration_range() -> None:
    op = operator(qod_profiles=("QOS_E", "QOS_L"), qod_inactive_profiles=("QOS_M",), qod_max_duration_s=20)
    listed = op.profiles({})
    assert listed.status == 200
    assert {p["name"]: p["status"] for p in listed.body} == {"QOS_E": "ACTIVE", "QOS_L": "ACTIVE",
                                                             "QOS_M": "INACTIVE"}  # fmt: skip
    assert fit(listed.body, "QOS_E", 600).duration_s == 20  # its maxDuration is the cap it enforces
    assert [p["name"] for p in op.profiles({"status": "INACTIVE"}).body] == ["QOS_M"]
    assert op.profile("QOS_L").body["maxDuration"] == {"value": 20, "unit": "Seconds"}
    assert op.profile("QOS_X").status == 404
    assert op.profiles({"colour": "red"}).status == 400
    assert op.profiles({"device": {"phoneNumber": "+46799999999"}}).status == 404
    # what the document's QosProfileDeviceRequest forbids is a 400, not a lookup (a list here was a 500)
    for bad in ({"device": [None]}, {"device": None}, {"status": "GONE"}, {"name": "x"}):
        assert op.profiles(bad).status == 400, bad


def test_an_inactive_profile_starts_no_session() -> None:
    op = operator(qod_inactive_profiles=("QOS_M",))
    body = {"device": {"phoneNumber": "+46700000001"}, "applicationServer": {"ipv4Address": "127.0.0.1"},
            "qosProfile": "QOS_M", "duration": 60}  # fmt: skip
    answer, _ = op.create(body)
    assert answer.status == 422
    assert answer.body["code"] == "QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE"


def test_each_profile_can_have_its_own_maximum_and_sessions_keep_to_it() -> None:
    op = operator(qod_max_duration_s=600, qod_profile_max_duration_s={"QOS_E": 20})
    caps = {p["name"]: p["maxDuration"]["value"] for p in op.profiles({}).body}
    assert caps == {"QOS_E": 20, "QOS_S": 600, "QOS_M": 600, "QOS_L": 600}
    body = {"device": {"phoneNumber": "+46700000001"}, "applicationServer": {"ipv4Address": "127.0.0.1"},
            "qosProfile": "QOS_E", "duration": 60}  # fmt: skip
    created, _ = op.create(body)
    assert created.body["duration"] == 20
    other, _ = op.create(body | {"qosProfile": "QOS_S", "applicationServerPorts": {"ports": [1]}})
    assert other.status == 409  # one session per device and flow, whatever its profile


def test_a_three_legged_token_sees_only_its_own_devices_sessions() -> None:
    op = operator()
    op.devices["uav2"] = {"phoneNumber": "+46700000002"}
    op.servers["uav2"] = "127.0.0.1"
    body = {"applicationServer": {"ipv4Address": "127.0.0.1"}, "qosProfile": "QOS_E", "duration": 60}
    mine, _ = op.create(body, subject="uav1")
    sid = mine.body["sessionId"]
    assert op.get(sid, subject="uav2").status == 404  # another device's token: no such session
    assert op.extend(sid, {"requestedAdditionalDuration": 5}, subject="uav2").status == 404
    assert op.delete(sid, subject="uav2")[0].status == 404
    assert op.get(sid, subject="uav1").status == 200
    assert op.delete(sid, subject="uav1")[0].status == 204
    refused, _ = op.create(body | {"device": {"phoneNumber": "+46700000001"}}, subject="uav1")
    assert (refused.status, refused.body["code"]) == (422, "UNNECESSARY_IDENTIFIER")
