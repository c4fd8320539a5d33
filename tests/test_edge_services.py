"""Router, planner, MPC and detector as real processes on 127.0.0.1, driven by a test client."""

from __future__ import annotations

import math
import re
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from dynqos.common import keys
from dynqos.common.config import ZenohConfig
from dynqos.common.depthcodec import encode_zstd16
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import CameraAck, CameraFrame, Command, Detections, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Bus, Priority, Received, Role, open_bus
from dynqos.onboard.pacing import split
from dynqos.sim.vehicle.dynamics import quat_to_rot
from dynqos.sim.vehicle.render import Renderer
from dynqos.sim.vehicle.world import default_world
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]


def drone_bus(zcfg: ZenohConfig) -> Bus:
    return open_bus(zcfg, Role.DRONE)


def _commands_for(zcfg: ZenohConfig, uavs: dict[str, float], wanted: int) -> dict[str, list[Command]]:
    """Publish 20 Hz States for each drone (at x = uavs[id]) until each has `wanted` Commands back."""
    bus = drone_bus(zcfg)
    commands: dict[str, list[Command]] = {uav: [] for uav in uavs}
    try:
        # announced, as each drone's daemon does: the MPC follows announced drones (held until the end)
        tokens = [bus.declare_token(keys.drone_presence(uav)) for uav in uavs]
        queue: BoundedQueue[Received] = BoundedQueue(1000)
        for uav in uavs:
            bus.subscribe(keys.downlink(uav, Downlink.COMMAND), queue)
        pubs = {
            uav: bus.publisher(keys.uplink(uav, Flow.PRIORITY, Stream.STATE), Priority.REAL_TIME)
            for uav in uavs
        }
        for pub in pubs.values():
            assert pub.wait_matched(20), "the MPC and planner never subscribed"
        deadline = time.monotonic() + 30
        seq = 0
        while min(len(c) for c in commands.values()) < wanted and time.monotonic() < deadline:
            seq += 1
            for uav, pub in pubs.items():
                pub.put(
                    State(
                        uav=uav,
                        seq=seq,
                        stamp_ns=time.monotonic_ns(),
                        pos_m=(uavs[uav], 0.0, -1.5),
                        vel_mps=(0.0, 0.0, 0.0),
                        quat=(1.0, 0.0, 0.0, 0.0),
                        rtt_est_ms=5.0,
                    )
                )
            end = time.monotonic() + 0.05  # 20 Hz states; collect what came back meanwhile
            while (item := queue.get(max(0.0, end - time.monotonic()))) is not None:
                assert isinstance(item.message, Command)
                commands[item.message.uav].append(item.message)
        del tokens
    finally:
        bus.close()
    for uav, got in commands.items():
        assert len(got) >= wanted, f"{uav}: only {len(got)} commands"
        assert all(c.uav == uav for c in got)
        assert [c.state_seq for c in got] == sorted(c.state_seq for c in got)
    return commands


# The MPC and the detector are tasks on the public API (common/builtin_tasks.py): `dynqos edge mpc` and
# `dynqos edge serve` of its declared Service are one path, so each test flies both.
SERVED_AS = {
    "mpc": (["edge", "mpc"], ["edge", "serve", "dynqos.edge.mpc.service:SERVICE", "--replica-id", "mpc-s"]),
    "detector": (["edge", "detector"], ["edge", "serve", "dynqos.edge.detector.service:SERVICE"]),
}


@pytest.mark.parametrize("served", [0, 1], ids=["edge-mpc", "edge-serve"])
def test_mpc_serves_two_drones_at_once(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]], served: int
) -> None:
    config, zcfg, procs = edge
    procs.append(DynqosProcess(["edge", "planner"], config))
    procs.append(DynqosProcess(SERVED_AS["mpc"][served], config))
    commands = _commands_for(zcfg, {"uav1": 0.0, "uav2": 3.0}, 40)
    for got in commands.values():
        assert got[-1].edge_hold_ns < 50_000_000
    # Both fly the planner's circle (lead-in 1 s to its start at (2, 0)): uav2 at x = 3 is pulled back.
    assert commands["uav2"][-1].accel_mps2[0][0] < 0
    assert commands["uav1"][-1].accel_mps2[0][0] > 0
    mpc_log = procs[-1].stop()
    assert "drones=2" in mpc_log
    assert "mpc: serving task mpc (20 Hz, deadline 150 ms, control flow)" in mpc_log
    if served:  # --replica-id names the replica that signs each Command (fencing)
        assert {c.replica for got in commands.values() for c in got} == {"mpc-s"}


def test_mpc_replicas_share_the_fleet_by_drone_id(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]],
) -> None:
    from dynqos.edge.mpc.service import shard_of

    config, zcfg, procs = edge
    procs.append(DynqosProcess(["edge", "planner"], config))
    replicas = [
        DynqosProcess(["edge", "mpc", "--set", "mpc.shard_count=2", "--set", f"mpc.shard_index={i}"], config)
        for i in (0, 1)
    ]
    procs.extend(replicas)
    uavs = [f"uav{i}" for i in range(1, 9)]
    by_shard = {shard: [u for u in uavs if shard_of(u, 2) == shard] for shard in (0, 1)}
    assert by_shard[0], "crc32 put every test drone on one shard"
    assert by_shard[1], "crc32 put every test drone on one shard"
    fleet = {by_shard[0][0]: 0.0, by_shard[1][0]: 1.0}
    commands = _commands_for(zcfg, fleet, 20)
    for got in commands.values():  # one answer per state: the other replica stays silent
        assert len({c.state_seq for c in got}) == len(got)
    for shard, replica in enumerate(replicas):
        log = replica.stop()
        assert f"shard={shard}/2 drones=1" in log, log[-500:]


def test_three_mpc_replicas_each_receive_only_the_drones_they_fly_or_stand_by_for(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]],
) -> None:
    """Per-drone subscriptions over a real router (edge/feeds.py): a replica that is neither primary nor
    standby for a drone receives none of its states (`not_mine=0`), and every drone is answered."""
    from dynqos.edge.replicas import ranked

    config, zcfg, procs = edge
    procs.append(DynqosProcess(["edge", "planner"], config))
    names = ("mpc-x", "mpc-y", "mpc-z")  # each ranks first or second for 3 to 5 of the six drones
    replicas = {name: DynqosProcess(["edge", "mpc"], config, env={"DYNQOS_MPC__REPLICA_ID": name})
                for name in names}  # fmt: skip
    procs.extend(replicas.values())
    uavs = {f"uav{i}": float(i % 3) for i in range(1, 7)}
    expected = {name: {uav for uav in uavs if name in ranked(uav, names)[:2]} for name in names}
    assert all(0 < len(e) < len(uavs) for e in expected.values()), expected  # each misses some
    _commands_for(zcfg, uavs, 20)  # its drones' tokens go when it ends
    for name, replica in replicas.items():
        log = replica.stop()
        followed = set(re.findall(r"mpc: following drone (\w+)", log))
        left = set(re.findall(r"mpc: no longer following drone (\w+) \(not ours now\)", log))
        assert followed - left == expected[name], log[-3000:]
        assert " not_mine=0 " in log[log.rindex("mpc: stopped") :]


@pytest.mark.parametrize("served", [0, 1], ids=["edge-detector", "edge-serve"])
def test_detector_acks_every_frame_and_finds_the_hoop(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]], served: int
) -> None:
    config, zcfg, procs = edge
    procs.append(DynqosProcess(SERVED_AS["detector"][served], config))
    world = default_world()
    renderer = Renderer(world, seed=3)
    pos = np.array([2.0, -2.2, -1.5])
    rot = quat_to_rot(np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]))  # facing +y
    rgb, depth = renderer.render(pos, rot)
    jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])[
        1
    ].tobytes()
    zdepth = encode_zstd16(np.round(depth * 1000).astype(np.uint16))
    bus = drone_bus(zcfg)
    try:
        acks: BoundedQueue[Received] = BoundedQueue(100)
        dets: BoundedQueue[Received] = BoundedQueue(100)
        bus.subscribe(keys.downlink("uav1", Downlink.CAMERA_ACK), acks)
        bus.subscribe(keys.downlink("uav1", Downlink.DETECTIONS), dets)
        rgb_pub = bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
        depth_pub = bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.CAMERA_DEPTH), Priority.DATA)
        assert rgb_pub.wait_matched(20)
        assert depth_pub.wait_matched(20)
        intr = renderer.intrinsics.as_tuple()
        got_acks: list[Received | None] = []
        for seq in range(1, 6):
            stamp = time.monotonic_ns()
            depth_pub.put(
                CameraFrame(
                    uav="uav1",
                    seq=seq,
                    stamp_ns=stamp,
                    kind="depth",
                    encoding="zstd16",
                    width=640,
                    height=480,
                    intrinsics=intr,
                    payload=zdepth,
                )
            )
            # rgb and depth travel on two keys, so zenoh may hand them over in either order; waiting for
            # the depth ack first makes the detector's newest depth the one that goes with this image.
            got_acks.append(acks.get(10))
            rgb_pub.put(
                CameraFrame(
                    uav="uav1",
                    seq=seq,
                    stamp_ns=stamp,
                    kind="rgb",
                    encoding="jpeg",
                    width=640,
                    height=480,
                    intrinsics=intr,
                    payload=jpeg,
                )
            )
            rgb_pub.put_bytes(b"\xc1 not a message")  # counted and dropped, never a crash
            got_acks.append(acks.get(10))
        detection = dets.get(20)
    finally:
        bus.close()
    assert all(isinstance(a.message, CameraAck) for a in got_acks if a is not None)
    assert sorted((a.message.frame_seq, a.message.kind) for a in got_acks if a) == sorted(  # type: ignore[attr-defined]
        (s, k) for s in range(1, 6) for k in ("depth", "rgb")
    )
    assert detection is not None
    assert isinstance(detection.message, Detections)
    hoop_center = renderer.project(np.array(world.hoops[0].center_m), pos, rot)
    assert hoop_center is not None
    found = [
        c
        for c in detection.message.circles_px
        if math.hypot(c[0] - hoop_center[0], c[1] - hoop_center[1]) < 8
    ]
    assert found, detection.message.circles_px
    index = detection.message.circles_px.index(found[0])
    located = detection.message.centers_m[index]
    assert located is not None
    assert located[2] == pytest.approx(2.2, abs=0.15)
    assert procs[-1].alive()
    log = procs[-1].stop()
    assert "rejected=" in log
    assert "detector: serving task detector (15 Hz, deadline 1000 ms, bulk flow)" in log


def test_detector_acks_a_paced_frame_once_its_last_part_is_in(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]],
) -> None:
    config, zcfg, procs = edge
    procs.append(DynqosProcess(["edge", "detector"], config))
    renderer = Renderer(default_world(), seed=3)
    _, depth = renderer.render(np.array([0.0, 0.0, -1.5]), quat_to_rot(np.array([1.0, 0.0, 0.0, 0.0])))
    payload = encode_zstd16(np.round(depth * 1000).astype(np.uint16))
    chunks = split(payload, 4096)
    assert len(chunks) >= 3
    whole = CameraFrame(uav="uav1", seq=0, stamp_ns=0, kind="depth", encoding="zstd16", width=640,
                        height=480, intrinsics=renderer.intrinsics.as_tuple(), payload=b"")  # fmt: skip
    bus = drone_bus(zcfg)
    try:
        acks: BoundedQueue[Received] = BoundedQueue(100)
        bus.subscribe(keys.downlink("uav1", Downlink.CAMERA_ACK), acks)
        pub = bus.publisher(keys.uplink("uav1", Flow.PRIORITY, Stream.CAMERA_DEPTH), Priority.INTERACTIVE_LOW)
        assert pub.wait_matched(20)

        def send(seq: int, parts: list[int]) -> None:
            for i in parts:
                pub.put(replace(whole, seq=seq, stamp_ns=seq, payload=chunks[i], part=i, parts=len(chunks)))

        everything = list(range(len(chunks)))
        send(1, everything)
        first = acks.get(20)
        send(2, everything[:-1])  # one part lost: never acked, given up once frame 3 completes
        send(3, everything[:-1])
        assert acks.get(1.0) is None  # frame 3 waits for its last part
        send(3, everything[-1:])
        third = acks.get(20)
    finally:
        bus.close()
    assert first is not None
    assert third is not None
    assert [(a.message.frame_seq, a.message.kind) for a in (first, third)] == [(1, "depth"), (3, "depth")]  # type: ignore[attr-defined]
    assert acks.get(0) is None
    log = procs[-1].stop()
    assert "frames=2 " in log
    assert "incomplete=1 " in log


def test_health_file_and_probe(edge: tuple[Path, ZenohConfig, list[DynqosProcess]], tmp_path: Path) -> None:
    """What the Kubernetes probes run: fresh health exits 0; stale, missing or foreign files exit 2."""
    import json
    import subprocess

    from tests.procs import DYNQOS

    config, _, procs = edge
    health = tmp_path / "planner.health"
    procs.append(DynqosProcess(["edge", "planner", "--health-file", str(health)], config))

    def probe(path: Path, max_age: str = "20") -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [DYNQOS, "health", str(path), "--max-age", max_age], capture_output=True, text=True, timeout=30
        )

    ok = probe(health)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("planner: ")
    record = json.loads(health.read_text())
    record["time_unix"] -= 100  # as if the service had hung 100 s ago
    stale = tmp_path / "stale.health"
    stale.write_text(json.dumps(record))
    foreign = tmp_path / "foreign.health"
    foreign.write_text("not json")
    cases = ((stale, "hung or stopped"), (tmp_path / "missing", "no health file"), (foreign, "not a"))
    for path, why in cases:
        out = probe(path)
        assert out.returncode == 2
        assert why in out.stderr
        assert out.stderr.count("\n") == 1


def _acked_once_each(zcfg: ZenohConfig, uavs: list[str], frames: int, first_seq: int) -> dict[str, list[int]]:
    """`frames` small RGB frames per drone, one at a time (each waits for its ack): the frame seqs
    acked, per drone, with any duplicate ack a second detector would send collected too."""
    image = np.full((48, 64, 3), 128, np.uint8)
    jpeg = cv2.imencode(".jpg", image)[1].tobytes()
    bus = drone_bus(zcfg)
    acked: dict[str, list[int]] = {uav: [] for uav in uavs}
    try:
        acks: BoundedQueue[Received] = BoundedQueue(1000)
        pubs = {}
        for uav in uavs:
            bus.subscribe(keys.downlink(uav, Downlink.CAMERA_ACK), acks, expect=(CameraAck,))
            pubs[uav] = bus.publisher(keys.uplink(uav, Flow.DEFAULT, Stream.CAMERA_RGB), Priority.DATA)
            assert pubs[uav].wait_matched(20)
        for seq in range(first_seq, first_seq + frames):
            for uav, pub in pubs.items():
                frame = CameraFrame(
                    uav=uav, seq=seq, stamp_ns=time.monotonic_ns(), kind="rgb", encoding="jpeg", width=64,
                    height=48, intrinsics=(50.0, 50.0, 32.0, 24.0), payload=jpeg,
                )  # fmt: skip
                pub.put(frame)
                item = acks.get(10)
                assert item is not None, f"{uav} frame {seq}: no ack"
                assert isinstance(item.message, CameraAck)
                acked[item.message.uav].append(item.message.frame_seq)
        late = acks.get(0.5)  # a second ack of the last frames would be here by now
        while late is not None:
            assert isinstance(late.message, CameraAck)
            acked[late.message.uav].append(late.message.frame_seq)
            late = acks.get_nowait()
    finally:
        bus.close()
    return acked


def test_two_detectors_share_the_drones_and_one_takes_all_when_the_other_goes(
    edge: tuple[Path, ZenohConfig, list[DynqosProcess]],
) -> None:
    """Each drone's frames are acked by exactly one detector (no duplicate acks); each detector serves
    the drones it ranks first for; killed, the other serves them all (edge/membership.py, LiveSet)."""
    from dynqos.edge.replicas import ranked

    config, zcfg, procs = edge
    names = ("det-a", "det-b")
    for name in names:
        env = {"DYNQOS_DETECTOR__REPLICA_ID": name, "DYNQOS_DETECTOR__HEALTH_INTERVAL_S": "0.5"}
        procs.append(DynqosProcess(["edge", "detector"], config, env=env))
    detectors = dict(zip(names, procs[-2:], strict=True))
    uavs = [f"uav{i}" for i in range(1, 9)]
    served = {name: [u for u in uavs if ranked(u, names)[0] == name] for name in names}
    assert all(served.values()), served  # eight drones: each detector ranks first for some
    acked = _acked_once_each(zcfg, uavs, frames=3, first_seq=1)
    assert acked == {uav: [1, 2, 3] for uav in uavs}  # once each, none twice
    logs = {}
    detectors["det-a"].proc.kill()  # its token goes with its session
    logs["det-a"] = detectors["det-a"].stop()
    acked = _acked_once_each(zcfg, uavs, frames=3, first_seq=4)
    assert acked == {uav: [4, 5, 6] for uav in uavs}
    logs["det-b"] = detectors["det-b"].stop()
    assert "replica det-a left (1 live)" in logs["det-b"]
    acks_b = [int(n) for n in re.findall(r" acks=(\d+)", logs["det-b"])]
    assert acks_b[-1] == 3 * len(served["det-b"]) + 3 * len(uavs)  # its drones, then all
