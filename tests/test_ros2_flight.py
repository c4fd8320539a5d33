"""The demo drone flies with `dynqos edge ros2` on its edge, and a ROS 2 client nobody here wrote (a raw
zenoh session on rmw_zenoh's keys, the ROBOTIS zenoh-ros2-sdk's discovery and publisher) sees its
topics with their types and hashes, decodes every pose, image and status it gets, each against what
the drone published, and steers it: a goal outside the arena is refused, a Path is flown (docs/ros2.md)."""

from __future__ import annotations

import csv
import queue
import threading
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import zenoh
from zenoh_ros2_sdk import get_topic_info, get_topic_names_and_types
from zenoh_ros2_sdk.session import ZenohSession

from dynqos.edge.ros2 import codec, wire
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import builtin_scenario
from tests.conftest import free_tcp_port
from tests.ros2_client import first_sample, ros_client, ros_pose, sdk_publisher

pytestmark = [pytest.mark.slow, pytest.mark.integration, pytest.mark.timeout(400)]

TARGET_ENU = (0.5, -0.5, 2.2)  # where the Path takes the drone: near the circle's centre, 0.7 m higher
POSES_BEFORE_STEERING = 100  # five seconds of poses at the drone's 20 Hz
DISCOVERY_TRIES = 5  # 2 s liveliness queries, until every topic is listed


def _key(topic: str, ros_type: str) -> str:
    return wire.topic_key(0, f"/dynqos/uav1/{topic}", ros_type, codec.type_hash(ros_type))


class Heard:
    """Every sample on one rmw_zenoh key, in arrival order."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.samples: list[tuple[bytes, bytes]] = []  # (payload, attachment)
        self.arrived: queue.Queue[int] = queue.Queue()
        self._lock = threading.Lock()
        self.subscriber = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        attachment = sample.attachment.to_bytes() if sample.attachment is not None else b""
        with self._lock:
            self.samples.append((sample.payload.to_bytes(), attachment))
            self.arrived.put(len(self.samples))

    def sequences(self) -> list[int]:
        return [wire.Attachment.decode(a).sequence for _, a in self.samples]


def _listed(port: int, names: list[str], tries: int = DISCOVERY_TRIES) -> dict[str, list[str]]:
    """`ros2 topic list -t` by the SDK's discovery, asked again (each a 2 s liveliness query) until every
    one of `names` is listed or `tries` queries have been asked: the SDK's first query opens its session
    to the router, and on a busy machine the router's replies can miss that query's 2 s (CI: none listed
    while the poses flowed). The last answer, whatever it lists."""
    listed: dict[str, list[str]] = {}
    for _ in range(tries):
        listed = dict(get_topic_names_and_types(domain_id=0, router_port=port, timeout=2.0))
        if all(name in listed for name in names):
            break
    return listed


def _fly(scenario: Any, out: Path, result: dict[str, Any]) -> None:
    result.update(run_scenario(scenario, out, progress=False))


def _recorded_states(folder: Path) -> list[tuple[float, float, float]]:
    with (folder / "states.csv").open() as f:
        return [(float(r["x_m"]), float(r["y_m"]), float(r["z_m"])) for r in csv.DictReader(f)]


def test_a_ros2_client_sees_every_pose_image_and_status_of_a_flying_drone_and_steers_it(
    tmp_path: Path,
) -> None:
    port = free_tcp_port()
    base = builtin_scenario("baseline")
    scenario = replace(
        base, name="ros2-flight", duration_s=30.0, ros2_bridge=True,
        config={**base.config, "zenoh": {"default_port": port, "priority_port": free_tcp_port()}},
    )  # fmt: skip
    out, result = tmp_path / "run", {}
    flight = threading.Thread(target=_fly, args=(scenario, out, result), daemon=True)
    flight.start()
    ros = ros_client(port, wait_s=60.0)  # the router the scenario starts
    publishers: list[Any] = []
    try:
        poses = Heard(ros, _key("pose", codec.POSE))
        images = Heard(ros, _key("camera/compressed", codec.COMPRESSED_IMAGE))
        infos = Heard(ros, _key("camera/camera_info", codec.CAMERA_INFO))
        statuses = Heard(ros, _key("status", codec.DIAGNOSTICS))
        outcomes: queue.Queue[zenoh.Sample] = queue.Queue()
        ros.declare_subscriber(_key("mission/status", codec.DIAGNOSTICS), outcomes.put)
        while poses.arrived.get(timeout=120) < POSES_BEFORE_STEERING:
            pass  # the drone took off and offloads: its poses reach ROS

        # `ros2 topic list -t` and `ros2 topic info -v`, by the SDK's discovery
        expected = {
            "pose": codec.POSE, "odom": codec.ODOMETRY, "camera/compressed": codec.COMPRESSED_IMAGE,
            "camera/camera_info": codec.CAMERA_INFO, "status": codec.DIAGNOSTICS, "mission": codec.PATH,
            "goal": codec.POSE,
        }  # fmt: skip
        listed = _listed(port, [f"/dynqos/uav1/{topic}" for topic in expected] + ["/tf"])
        for topic, ros_type in expected.items():
            assert listed.get(f"/dynqos/uav1/{topic}") == [ros_type], (topic, sorted(listed))
        assert listed.get("/tf") == [codec.TF], sorted(listed)
        info = get_topic_info("/dynqos/uav1/pose", domain_id=0, router_port=port, timeout=2.0, verbose=True)
        assert info is not None
        assert [p.type_hash for p in info.publishers] == [codec.type_hash(codec.POSE)]

        # steering: a goal outside the arena is refused, a Path is flown
        t = ZenohSession.get_instance("127.0.0.1", port).store.types
        goal = sdk_publisher(port, "/dynqos/uav1/goal", codec.POSE)
        path = sdk_publisher(port, "/dynqos/uav1/mission", codec.PATH)
        publishers += [goal, path]
        far = ros_pose(t, (0.0, 80.0, 2.0))
        refused = first_sample(outcomes, lambda: goal.publish(header=far.header, pose=far.pose), tries=25)
        (error,) = codec.decode(codec.DIAGNOSTICS, refused.payload.to_bytes()).status
        assert error.level == codec.ERROR
        assert "outside the arena" in error.message
        there = [ros_pose(t, TARGET_ENU)]
        accepted = first_sample(outcomes, lambda: path.publish(header=there[0].header, poses=there), tries=25)
        (ok,) = codec.decode(codec.DIAGNOSTICS, accepted.payload.to_bytes()).status
        assert ok.level == codec.OK, ok.message
        flight.join(timeout=300)
        assert not flight.is_alive()
    finally:
        for publisher in publishers:
            publisher.close()
        ros.close()
    assert result["ok"] is True, result["failure"]
    folder = out / scenario.run_id
    states = _recorded_states(folder)
    target_ned = (TARGET_ENU[1], TARGET_ENU[0], -TARGET_ENU[2])
    # the drone went where the Path said and held there: its last 2 s of recorded states, within 0.25 m
    for position in states[-100:]:
        assert np.linalg.norm(np.subtract(position, target_ned)) < 0.25, position

    # Every pose, counted: the recorded states are what the drone published; the poses that match them
    # match a contiguous run of them (the bridge dropped none and made none up), covering most of the flight.
    index = {state: i for i, state in enumerate(states)}
    matched = []
    for payload, _ in poses.samples:
        p = codec.decode(codec.POSE, payload).pose.position
        matched.append(index.get((p.y, p.x, -p.z)))  # ENU back to NED, exactly: the same floats
    found = [i for i in matched if i is not None]
    print(f"{len(poses.samples)} poses ({len(found)} of the {len(states)} recorded states, in order), "
          f"{len(images.samples)} images, {len(statuses.samples)} statuses; the drone ended "
          f"{np.linalg.norm(np.subtract(states[-1], target_ned)):.3f} m from the Path's end")  # fmt: skip
    assert found == list(range(found[0], found[0] + len(found)))
    assert len(found) > 0.8 * len(states)
    assert matched[matched.index(found[0]) : matched.index(found[-1]) + 1] == found  # no stranger between
    for heard in (poses, images, infos, statuses):  # every sample with rmw_zenoh's attachment, none lost
        sequences = heard.sequences()
        assert sequences == list(range(sequences[0], sequences[0] + len(sequences)))
    # Every image a JPEG of the size its CameraInfo gives; every status one of the drone's.
    sizes = set()
    for payload, _ in infos.samples:
        camera_info = codec.decode(codec.CAMERA_INFO, payload)
        sizes.add((camera_info.width, camera_info.height))
    assert len(images.samples) > 5 * scenario.duration_s  # 15 fps at the camera, whatever the rate limits
    for payload, _ in images.samples:
        data = codec.decode(codec.COMPRESSED_IMAGE, payload).data
        image = cv2.imdecode(np.frombuffer(bytes(data), np.uint8), cv2.IMREAD_COLOR)
        assert image is not None
        assert (image.shape[1], image.shape[0]) in sizes
    # Every status the flight recorded was heard with the same values (counted: as many times each).
    with (folder / "supervisor.csv").open() as f:
        recorded = Counter(
            (r["state"], r["flow"], r["control_source"], r["risk"], r["latency"],
             f"{float(r['rtt_ms']):.1f}" if r["rtt_ms"] else "")
            for r in csv.DictReader(f)
        )  # fmt: skip
    heard: Counter[tuple[str, ...]] = Counter()
    for payload, _ in statuses.samples:
        (status,) = codec.decode(codec.DIAGNOSTICS, payload).status
        v = {kv.key: kv.value for kv in status.values}
        heard[(v["state"], v["flow"], v["control"], v["risk"], v["latency"], v["rtt_ms"])] += 1
    assert sum(recorded.values()) > 4 * scenario.duration_s  # 5 Hz
    assert recorded - heard == Counter(), recorded - heard
