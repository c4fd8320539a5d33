"""`dynqos record --ros2` read back with the mcap project's own ROS 2 decoder (mcap-ros2-support): the
file says it is a ROS 2 recording, each topic has its ros2msg schema and cdr encoding, and every message
decodes; what the drone published is all there, counted (docs/ros2.md)."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from dynqos.common import keys
from dynqos.common.config import load_config
from dynqos.common.keys import Flow, Stream
from dynqos.common.messages import State
from dynqos.common.transport import Priority, Role, default_flow_endpoint, open_bus
from tests.conftest import flow_ports_toml
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

STATES = 25


def test_a_ros2_recording_decodes_whole_with_the_mcap_ros2_decoder(tmp_path: Path) -> None:
    config_path = tmp_path / "edge.toml"
    config_path.write_text(f"[zenoh]\n{flow_ports_toml()}")
    config = load_config(config_path)
    out = tmp_path / "flight.mcap"
    router = DynqosProcess(["edge", "router"], config_path)
    recorder = DynqosProcess(["record", "--ros2", "--out", str(out)], config_path)
    drone = open_bus(config.zenoh, Role.DRONE, connect=[default_flow_endpoint(config.zenoh)])
    try:
        publisher = drone.publisher(keys.uplink("uav3", Flow.DEFAULT, Stream.STATE), Priority.DATA_HIGH)
        assert publisher.wait_matched(10)  # the recorder subscribes to every drone's state
        h = math.sqrt(0.5)
        for k in range(1, STATES + 1):
            state = State(uav="uav3", seq=k, stamp_ns=k, pos_m=(0.1 * k, 0.0, -2.0), vel_mps=(0.0,) * 3,
                          quat=(h, 0.0, 0.0, h))  # fmt: skip
            publisher.put(state)
    finally:
        drone.close()
        log = recorder.stop()  # SIGTERM: what is in flight is still written, then the file is closed whole
        router.stop()
    assert "Traceback" not in log, log[-2000:]
    topics: Counter[str] = Counter()
    with out.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        assert header.profile == "ros2"
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert schema is not None
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            assert "offered_qos_profiles" in channel.metadata
            topics[channel.topic] += 1
            if channel.topic == "/dynqos/uav3/pose":
                assert decoded.pose.position.y == pytest.approx(0.1 * message.sequence)  # north is ENU y
                assert decoded.pose.position.z == pytest.approx(2.0)
    assert topics == {"/dynqos/uav3/pose": STATES, "/dynqos/uav3/odom": STATES, "/tf": STATES}
