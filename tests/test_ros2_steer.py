"""ROS 2 steering, pure: a nav_msgs/Path or a goal PoseStamped (CDR from rosbags, in ENU) becomes a
MissionRequest in NED that starts where the drone is, or a refusal that says why; the planner flies a
request from now, once per seq, and never one outside its arena (docs/ros2.md)."""

from __future__ import annotations

import logging
import math
from typing import Any

import pytest

from dynqos.common import keys
from dynqos.common.acl import ros2_steering
from dynqos.common.bus import MemoryBus
from dynqos.common.clock import FakeClock
from dynqos.common.config import PlannerConfig, load_config
from dynqos.common.errors import ConfigError
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import MissionRequest, Reference, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received
from dynqos.edge.planner.service import PlannerService
from dynqos.edge.ros2 import codec, wire
from dynqos.edge.ros2.steer import KINDS, Refusal, Steering
from dynqos.edge.runtime import Ports
from tests.edge_cores import take

ARENA = ((-10.0, -10.0, -8.0), (10.0, 10.0, -0.3))
HERE = (1.0, 2.0, -1.5)  # the drone, NED


def _pose(t: Any, enu: tuple[float, float, float], frame: str) -> Any:
    zero = t["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    level = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    position = t["geometry_msgs/msg/Point"](x=enu[0], y=enu[1], z=enu[2])
    return t[codec.POSE](header=t["std_msgs/msg/Header"](stamp=zero, frame_id=frame),
                         pose=t["geometry_msgs/msg/Pose"](position=position, orientation=level))  # fmt: skip


def path(points_enu: list[tuple[float, float, float]], frame: str = "map") -> bytes:
    t = codec.STORE.types
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id=frame
    )
    return codec.encode(t[codec.PATH](header=header, poses=[_pose(t, p, frame) for p in points_enu]))


def goal(enu: tuple[float, float, float], frame: str = "map") -> bytes:
    return codec.encode(_pose(codec.STORE.types, enu, frame))


def test_a_path_becomes_a_mission_in_ned_from_where_the_drone_is() -> None:
    steering = Steering("map", *ARENA)
    got = steering.request("uav1", "mission", path([(2.0, 1.0, 1.5), (4.0, 1.0, 2.0)]), HERE, 7, 100)
    assert isinstance(got, MissionRequest)
    assert got.waypoints_m == (HERE, (1.0, 2.0, -1.5), (1.0, 4.0, -2.0))
    assert (got.uav, got.seq, got.stamp_ns, got.source) == ("uav1", 7, 100, "ros2:mission")
    one = steering.request("uav1", "goal", goal((-3.0, 5.0, 2.0)), HERE, 8, 200)
    assert isinstance(one, MissionRequest)
    assert one.waypoints_m == (HERE, (5.0, -3.0, -2.0))


@pytest.mark.parametrize(
    ("kind", "payload", "position", "reason"),
    [
        ("goal", goal((30.0, 0.0, 2.0)), HERE, "waypoint 0 (0.00, 30.00, -2.00) NED is outside the arena: y"),
        ("goal", goal((0.0, 0.0, 0.0)), HERE, "outside the arena: z must be in -8..-0.3 m"),  # the ground
        ("mission", path([(1.0, 1.0, 1.0), (1.0, 1.0, 50.0)]), HERE, "waypoint 1"),
        ("mission", path([(1.0, 1.0, 1.0)], frame="odom"), HERE, "frame 'odom' is not the bridge's 'map'"),
        ("mission", path([]), HERE, "no waypoint"),
        ("mission", path([(math.nan, 1.0, 1.0)]), HERE, "not finite"),
        ("mission", path([(1.0, 1.0, 1.0)] * 300), HERE, "300 waypoints (at most 255)"),
        ("goal", goal((1.0, 1.0, 1.0)), None, "no state from uav1 yet"),
        ("goal", b"\x00\x01\x00\x00junk", HERE, "not a geometry_msgs/msg/PoseStamped in CDR"),
        ("mission", goal((1.0, 1.0, 1.0)), HERE, "not a nav_msgs/msg/Path in CDR"),
    ],
)
def test_a_bad_mission_or_goal_is_refused_with_its_reason(
    kind: str, payload: bytes, position: tuple[float, float, float] | None, reason: str
) -> None:
    got = Steering("map", *ARENA).request("uav1", kind, payload, position, 1, 0)
    assert isinstance(got, Refusal)
    assert reason in got.reason
    assert (got.uav, got.kind) == ("uav1", kind)


def test_the_acl_lets_ros2_nodes_write_exactly_the_keys_the_bridge_listens_on() -> None:
    """The router's rule names the DDS types as rmw_zenoh spells them; `mission/status` is not among them."""
    rules = ros2_steering(0, "dynqos")
    for rule, (kind, ros_type) in zip(rules, KINDS.items(), strict=True):
        key = wire.topic_key(0, f"/dynqos/uav1/{kind}", ros_type, codec.type_hash(ros_type))
        prefix, _, last = rule.rpartition("/")
        assert last == "*"
        assert key.rpartition("/")[0] == prefix.replace("*", "uav1")
    status = wire.topic_key(
        0, "/dynqos/uav1/mission/status", codec.DIAGNOSTICS, codec.type_hash(codec.DIAGNOSTICS)
    )
    assert not any(status.startswith(rule.rpartition("/")[0].replace("*", "uav1")) for rule in rules)


def test_an_arena_that_is_not_a_box_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="arena_max_m"):
        PlannerConfig(arena_min_m=(0.0, 0.0, -5.0), arena_max_m=(10.0, 0.0, -0.3))


def test_the_planner_flies_a_mission_from_now_once_per_seq_and_refuses_one_outside_its_arena(
    caplog: pytest.LogCaptureFixture,
) -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    settings = [
        'planner.mission="hover"',
        "planner.arena_min_m=[-10, -10, -8]",
        "planner.arena_max_m=[10, 10, -0.3]",
    ]
    planner = PlannerService(load_config(None, settings), Ports(bus, clock))
    bus.declare_token(keys.drone_presence("uav1"))
    planner.discover(clock.now_ns())  # it follows uav1 from here
    refs: BoundedQueue[Received] = BoundedQueue(100)
    bus.subscribe(keys.downlink("uav1", Downlink.REFERENCE), refs)
    state = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
    mission = bus.publisher(keys.downlink("uav1", Downlink.MISSION), Priority.DATA)

    def tick(seconds: float) -> Reference:
        clock.advance_s(seconds)
        bus.pump()
        take(planner, clock.now_ns())
        planner.discover(clock.now_ns())
        planner.publish()
        bus.pump()
        last = refs.drain()[-1].message
        assert isinstance(last, Reference)
        return last

    state.put(
        State(uav="uav1", seq=1, stamp_ns=0, pos_m=HERE, vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0))
    )
    assert tick(0.1).pos_m[0] == pytest.approx((0.0, 0.0, -1.5))  # the configured hover
    ask = MissionRequest(uav="uav1", seq=5, stamp_ns=0, waypoints_m=(HERE, (1.0, 6.0, -1.5)), speed_mps=1.0)
    mission.put(ask)
    first = tick(0.1)
    # from where the drone was when it arrived (0.1 s ago), east at 1 m/s
    assert first.pos_m[0] == pytest.approx((1.0, 2.1, -1.5), abs=0.01)
    assert first.pos_m[10] == pytest.approx((1.0, 2.1 + 10 * first.dt_s, -1.5), abs=0.01)
    mission.put(ask)  # re-sent: the same mission goes on, it does not start again
    later = tick(2.0)
    assert later.pos_m[0][1] == pytest.approx(2.0 + 2.1, abs=0.01)
    with caplog.at_level(logging.WARNING):
        mission.put(MissionRequest(uav="uav1", seq=6, stamp_ns=0, waypoints_m=(HERE, (1.0, 60.0, -1.5))))
        refused = tick(0.1)
    assert refused.pos_m[0][1] == pytest.approx(4.2, abs=0.01)  # still the mission it flew
    assert planner.missions_refused == 1
    assert planner.missions_flown == 1
    assert (
        "refused mission 6 for uav1 from ?, never flown: waypoint 1 (1.00, 60.00, -1.50) NED" in caplog.text
    )


def test_a_scenario_with_the_bridge_needs_the_ros2_extra_and_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    from dataclasses import replace

    from dynqos.plan import scenario as scenarios

    base = scenarios.builtin_scenario("baseline")
    assert replace(base, ros2_bridge=True).ros2_bridge  # here the extra is installed
    real = scenarios.importlib.util.find_spec
    monkeypatch.setattr(
        scenarios.importlib.util, "find_spec", lambda name: None if name == "rosbags" else real(name)
    )
    with pytest.raises(ConfigError, match=r"ros2_bridge.*needs the ros2 extra: pip install 'dynqos\[ros2\]'"):
        replace(base, ros2_bridge=True)
