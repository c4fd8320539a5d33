from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dynqos.common import keys
from dynqos.common.errors import KeyExprError
from dynqos.common.keys import Downlink, DownlinkKey, Flow, Stream, UplinkKey

uav_ids = st.from_regex(keys.UAV_ID_PATTERN, fullmatch=True)


@given(uav=uav_ids, flow=st.sampled_from(Flow), stream=st.sampled_from(Stream))
def test_uplink_key_round_trips(uav: str, flow: Flow, stream: Stream) -> None:
    key = keys.uplink(uav, flow, stream)
    assert key == f"dynqos/{uav}/up/{flow.value}/{stream.value}"
    assert keys.parse(key) == UplinkKey(uav, flow, stream)


@given(uav=uav_ids, kind=st.sampled_from(Downlink))
def test_downlink_key_round_trips(uav: str, kind: Downlink) -> None:
    assert keys.parse(keys.downlink(uav, kind)) == DownlinkKey(uav, kind)


def test_design_keys_are_spelled_as_in_design() -> None:
    assert keys.uplink("uav1", Flow.PRIORITY, Stream.CAMERA_RGB) == "dynqos/uav1/up/priority/camera/rgb"
    assert keys.uplink_any_flow("uav1", Stream.STATE) == "dynqos/uav1/up/*/state"
    assert keys.uplink_all_drones(Stream.STATE) == "dynqos/*/up/*/state"
    assert keys.downlink("uav1", Downlink.COMMAND) == "dynqos/uav1/down/cmd"
    assert keys.downlink("uav1", Downlink.CAMERA_ACK) == "dynqos/uav1/down/ack/camera"
    assert keys.downlink("uav1", Downlink.DETECTIONS) == "dynqos/uav1/down/detections"
    assert keys.downlink("uav1", Downlink.REFERENCE) == "dynqos/uav1/ref"
    assert keys.downlink_all_drones(Downlink.REFERENCE) == "dynqos/*/ref"


@pytest.mark.parametrize("bad", ["", "a" * 33, "uav 1", "uav/1", "uav*", "ü", "a.b", "$*", "uav1\n"])
def test_bad_drone_ids_are_rejected_with_the_rule(bad: str) -> None:
    with pytest.raises(KeyExprError, match="1 to 32 characters"):
        keys.uplink(bad, Flow.DEFAULT, Stream.STATE)


def test_non_string_drone_id_is_rejected() -> None:
    with pytest.raises(KeyExprError, match="must be a string"):
        keys.check_uav_id(7)


@pytest.mark.parametrize(
    ("key", "reason"),
    [
        ("zenoh/uav1/up/default/state", "not a dynqos key"),
        ("dynqos", "not a dynqos key"),
        ("dynqos/uav1/up/fast/state", "unknown flow"),
        ("dynqos/uav1/up/default/lidar", "unknown stream"),
        ("dynqos/uav1/up/default", "needs a flow and a stream"),
        ("dynqos/uav1/down/nothing", "unknown key kind"),
        ("dynqos/bad id/down/cmd", "1 to 32 characters"),
    ],
)
def test_parse_names_what_is_wrong(key: str, reason: str) -> None:
    with pytest.raises(KeyExprError, match=reason):
        keys.parse(key)


def test_parse_rejects_non_string() -> None:
    with pytest.raises(KeyExprError, match="must be a string"):
        keys.parse(b"dynqos/uav1/down/cmd")  # type: ignore[arg-type]


def test_one_replica_id_rule_for_config_tokens_and_our_own() -> None:
    from dynqos.common.keys import check_replica_id, valid_replica_id

    assert valid_replica_id("mpc-a_1")
    assert valid_replica_id("x" * 64)
    for bad in ("", "x" * 65, "a/b", "a b", "é", "a\n"):
        assert not valid_replica_id(bad), bad
    with pytest.raises(ValueError, match=r"agent id 'a/b' is invalid: use 1 to 64 characters"):
        check_replica_id("a/b", "agent id")


def test_a_flood_is_logged_at_its_first_and_every_thousandth() -> None:
    from dynqos.common.floods import worth_logging

    assert [n for n in range(0, 3001) if worth_logging(n)] == [1, 1000, 2000, 3000]
    assert [n for n in range(0, 201) if worth_logging(n, every=100)] == [1, 100, 200]
