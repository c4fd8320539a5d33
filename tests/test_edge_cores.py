"""The edge services' cores driven as the runtime drives them (tests/edge_cores.py), on a MemoryBus and
a fake clock: the detector, the ROS 2 bridge, the QoS agent and the planner's mission clock (the MPC,
the planners' replicas: test_replicas, test_feeds, test_fleet_service, test_ros2_steer)."""

from __future__ import annotations

import cv2

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority, Received
from dynqos.common.clock import FakeClock
from dynqos.common.config import load_config
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import (
    CameraAck,
    CameraFrame,
    Detections,
    MissionRequest,
    QosRequest,
    Reference,
    State,
)
from dynqos.common.queues import BoundedQueue
from dynqos.edge.detector.service import DetectorService
from dynqos.edge.planner.service import PlannerService
from dynqos.edge.qos.agent import QosAgent
from dynqos.edge.ros2 import codec, wire
from dynqos.edge.ros2.service import Ros2Face
from dynqos.edge.runtime import Ports
from tests.edge_cores import take, turn
from tests.test_detector import rendered_hoop_views
from tests.test_ros2_steer import path

HERE = (1.0, 2.0, -1.5)


def _listen(bus: MemoryBus, key: str) -> BoundedQueue[Received]:
    queue: BoundedQueue[Received] = BoundedQueue(100)
    bus.subscribe(key, queue)
    return queue


def _frame(seq: int, stamp_ns: int) -> CameraFrame:
    rgb, _depth, _truth, _dist, _radius, renderer = rendered_hoop_views(1)[0]
    jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes()
    height, width = rgb.shape[:2]
    k = renderer.intrinsics
    return CameraFrame(uav="uav1", seq=seq, stamp_ns=stamp_ns, kind="rgb", encoding="jpeg", width=width,
                       height=height, intrinsics=(k.fx, k.fy, k.cx, k.cy), payload=jpeg)  # fmt: skip


def test_the_detector_acks_a_frame_on_arrival_with_its_hold_and_finds_the_hoop_after() -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    detector = DetectorService(load_config(None, ['detector.replica_id="d-a"']), Ports(bus, clock))
    acks = _listen(bus, keys.downlink("uav1", Downlink.CAMERA_ACK))
    found = _listen(bus, keys.downlink("uav1", Downlink.DETECTIONS))
    camera = bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
    camera.put(_frame(7, clock.now_ns()))
    clock.advance_s(0.002)  # the frame waited 2 ms in the inbox
    turn(detector, clock.now_ns())
    ack = acks.drain()[0].message
    assert isinstance(ack, CameraAck)
    assert (ack.frame_seq, ack.edge_hold_ns) == (7, 2_000_000)
    assert found.drain() == []  # the search is the detector's own thread's, not the ack's
    assert detector.detect_next(0.0)
    detections = found.drain()[0].message
    assert isinstance(detections, Detections)
    assert detections.frame_seq == 7
    assert len(detections.circles_px) >= 1


def test_a_detector_ranked_second_for_the_drone_leaves_its_frames_to_the_first() -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    a = DetectorService(load_config(None, ['detector.replica_id="d-a"']), Ports(bus, clock))
    b = DetectorService(load_config(None, ['detector.replica_id="d-b"']), Ports(bus, clock))
    acks = _listen(bus, keys.downlink("uav1", Downlink.CAMERA_ACK))
    bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA).put(_frame(1, 0))
    for detector in (a, b):
        turn(detector, clock.now_ns())
    assert len(acks.drain()) == 1  # acked once, by the one that serves uav1
    assert sorted([a.counters["others"], b.counters["others"]]) == [0, 1]


def test_the_ros2_bridge_shows_a_state_as_a_pose_and_turns_a_ros_path_into_a_mission() -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    bridge = Ros2Face(load_config(None, ["ros2.publish_period_s=0"]), Ports(bus))
    missions = _listen(bus, keys.downlink("uav1", Downlink.MISSION))
    pose_key = wire.topic_key(0, "/dynqos/uav1/pose", codec.POSE, codec.type_hash(codec.POSE))
    state = State(
        uav="uav1", seq=1, stamp_ns=0, pos_m=HERE, vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0)
    )
    bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME).put(state)
    take(bridge, clock.now_ns())
    assert bus.published.get(pose_key) == 1
    mission_key = wire.topic_key(0, "/dynqos/uav1/mission", codec.PATH, codec.type_hash(codec.PATH))
    bus.publisher(mission_key, Priority.DATA).put_bytes(path([(2.0, 1.0, 1.5), (4.0, 1.0, 1.5)]))
    turn(bridge, clock.now_ns())
    request = missions.drain()[0].message
    assert isinstance(request, MissionRequest)
    assert request.waypoints_m[0] == HERE  # from where the drone is
    assert request.waypoints_m[-1] == (1.0, 4.0, -1.5)  # ENU (4, 1, 1.5) in NED


def test_the_qos_agent_keeps_each_drones_wish_from_its_requests() -> None:
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    agent = QosAgent(load_config(None, ['qos.backend="links"']), Ports(bus, clock))
    ask = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.QOS), Priority.INTERACTIVE_HIGH)
    ask.put(QosRequest(uav="uav1", seq=1, stamp_ns=clock.now_ns(), want=True, risk="HR"))
    turn(agent, clock.now_ns())
    grant = agent.drones["uav1"].grant
    assert grant.wanted
    ask.put(QosRequest(uav="uav1", seq=2, stamp_ns=clock.now_ns(), want=False, risk="LR"))
    turn(agent, clock.now_ns())
    assert not grant.wanted
    assert agent.drones["uav1"].need.risk == "LR"


def test_the_planners_mission_starts_when_the_drone_can_follow_it_not_while_it_takes_off() -> None:
    """PX4 takes 10 s to take off where our vehicle takes 3: a mission clock started at the drone's first
    state had run on by then, and the drone flew straight across its circle to catch up."""
    clock = FakeClock(1_000_000_000)
    bus = MemoryBus(clock)
    planner = PlannerService(load_config(None, ['planner.mission="circle"']), Ports(bus, clock))
    bus.declare_token(keys.drone_presence("uav1"))
    refs = _listen(bus, keys.downlink("uav1", Downlink.REFERENCE))
    drone = bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.STATE), Priority.REAL_TIME)

    def fly(seconds: float, mode: str) -> list[Reference]:
        for k in range(round(seconds / 0.1)):
            drone.put(State(uav="uav1", seq=k, stamp_ns=clock.now_ns(), pos_m=(0.0, 0.0, -1.0),
                            vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0), mode=mode))  # fmt: skip
            bus.pump()
            turn(planner, clock.now_ns())
            bus.pump()
            clock.advance_s(0.1)
        return [i.message for i in refs.drain() if isinstance(i.message, Reference)]

    assert fly(10.0, "standby") == []  # on the ground and climbing: nothing to follow yet
    flown = fly(2.0, "offboard")
    assert flown, "no reference once the drone flies offboard"
    assert flown[0].mission_t_s < 0.15  # the mission begins here, not 10 s along
    assert flown[-1].mission_t_s > 1.5
