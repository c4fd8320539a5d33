"""Key expressions: every zenoh key dynqos uses is built and parsed here (docs/architecture.md).

A 5G QoS flow is a zenoh link with a priority range; the key names the flow the publisher was
declared on, so a receiver subscribes to both flows with one wildcard:

    dynqos/<uav>/up/<flow>/<stream>       flow in {default, priority}
    dynqos/<uav>/up/*/<stream>            what the edge subscribes to
    dynqos/<uav>/down/cmd                 MPC -> drone commands
    dynqos/<uav>/down/ack/camera          detector -> drone camera acks
    dynqos/<uav>/down/detections          detector -> drone detections
    dynqos/<uav>/ref                      planner -> MPC reference
    dynqos/<uav>/mission                  ROS 2 bridge -> planner: a mission from outside (MissionRequest)
    dynqos/<uav>/up/<flow>/qos            drone -> QoS agent: priority wanted or not (QosRequest)
    dynqos/<uav>/down/qos                 QoS agent -> drone: the network's grant (QosGrant)
    dynqos/<uav>/down/qos/decision        QoS agent's arbiter -> drone and tools (QosDecision)
    dynqos/<uav>/down/qos/monitoring      QoS agent -> drone: the core's delay reports (QosMonitoring)
    dynqos/<uav>/up/<flow>/task/<name>    drone -> a user's task at the edge (TaskRequest)
    dynqos/<uav>/down/task/<name>         the task's edge service -> drone (TaskAnswer)
    dynqos/<uav>/clock                    drone -> router -> drone: the preflight's clock probes
    dynqos/<uav>/alive                    liveliness token of a drone, held while its session lives
    dynqos/<uav>/watch/mpc/<group>        the MPC holding a drone -> its standby: a few of its States
    dynqos/edge/replicas/<service>/<group>/<id>
                                          liveliness token of one replica of an edge service
    dynqos/edge/replicas/qos/<group>/active/<id>
                                          held by the QoS agent that holds the operator sessions
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

from dynqos.common.errors import KeyExprError
from dynqos.common.modes import Flow as Flow  # re-exported: a key names its flow

ROOT = "dynqos"
UAV_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,32}")
# An edge replica's id: the last chunk of its liveliness token (MPC, planner, detector, QoS agent) and
# what a Command's `replica` names; one rule for the config, the tokens seen and our own.
REPLICA_ID_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,64}")
REPLICA_ID_RULE = "use 1 to 64 characters from A-Z a-z 0-9 _ -"


def valid_replica_id(name: str) -> bool:
    return REPLICA_ID_PATTERN.fullmatch(name) is not None


def check_replica_id(name: str, what: str = "replica id") -> None:
    """ValueError naming the id (cut to 80 characters) and the rule, when `name` breaks it."""
    if not valid_replica_id(name):
        raise ValueError(f"{what} {name[:80]!r} is invalid: {REPLICA_ID_RULE}")


class Stream(str, enum.Enum):
    STATE = "state"
    CAMERA_RGB = "camera/rgb"
    CAMERA_DEPTH = "camera/depth"
    STATUS = "status"
    QOS = "qos"


class Downlink(str, enum.Enum):
    COMMAND = "down/cmd"
    CAMERA_ACK = "down/ack/camera"
    DETECTIONS = "down/detections"
    REFERENCE = "ref"
    QOS_GRANT = "down/qos"
    QOS_DECISION = "down/qos/decision"
    QOS_MONITORING = "down/qos/monitoring"
    MISSION = "mission"  # edge to edge, as REFERENCE: the ROS 2 bridge to the planner replicas


def check_uav_id(uav: object) -> str:
    """Return `uav` if it is a valid drone id, else raise KeyExprError saying why."""
    if not isinstance(uav, str):
        raise KeyExprError(f"drone id must be a string, got {type(uav).__name__}")
    if not UAV_ID_PATTERN.fullmatch(uav):
        raise KeyExprError(f"drone id {uav[:40]!r} is invalid: use 1 to 32 characters from A-Z a-z 0-9 _ -")
    return uav


def uplink(uav: str, flow: Flow, stream: Stream) -> str:
    return f"{ROOT}/{check_uav_id(uav)}/up/{Flow(flow).value}/{Stream(stream).value}"


def uplink_any_flow(uav: str, stream: Stream) -> str:
    """What a receiver subscribes to: one stream of one drone, on both flows."""
    return f"{ROOT}/{check_uav_id(uav)}/up/*/{Stream(stream).value}"


def uplink_all_drones(stream: Stream) -> str:
    """One stream of every drone on both flows (the MPC discovers drones this way)."""
    return f"{ROOT}/*/up/*/{Stream(stream).value}"


def downlink(uav: str, kind: Downlink) -> str:
    return f"{ROOT}/{check_uav_id(uav)}/{Downlink(kind).value}"


def downlink_all_drones(kind: Downlink) -> str:
    return f"{ROOT}/*/{Downlink(kind).value}"


TASK_NAME_PATTERN = re.compile(r"[a-z][a-z0-9-]{0,31}")
TASK_NAME_RULE = "use 1 to 32 characters from a-z 0-9 -, starting with a letter"


def check_task_name(name: object) -> str:
    """Return `name` if it can name an offloaded task (a key chunk, a service name), else raise."""
    if not isinstance(name, str) or TASK_NAME_PATTERN.fullmatch(name) is None:
        raise KeyExprError(f"task name {str(name)[:40]!r} is invalid: {TASK_NAME_RULE}")
    return name


def task_uplink(uav: str, flow: Flow, task: str) -> str:
    """A drone's requests to a user's task (docs/offload.md), on the flow they ride."""
    return f"{ROOT}/{check_uav_id(uav)}/up/{Flow(flow).value}/task/{check_task_name(task)}"


def task_uplink_all_drones(task: str) -> str:
    """What a task's edge service subscribes to: every drone's requests, on both flows."""
    return f"{ROOT}/*/up/*/task/{check_task_name(task)}"


def task_downlink(uav: str, task: str) -> str:
    return f"{ROOT}/{check_uav_id(uav)}/down/task/{check_task_name(task)}"


def clock_probe(uav: str) -> str:
    """Where the preflight puts and hears its own probes, so that the router stamps them with its clock
    (onboard/clock_offset.py); only that drone may use it."""
    return f"{ROOT}/{check_uav_id(uav)}/clock"


def drone_presence(uav: str) -> str:
    """The drone's liveliness token: the edge replicas subscribe to the drones they see here
    (edge/feeds.py), so a drone that holds none is served by no MPC or planner."""
    return f"{ROOT}/{check_uav_id(uav)}/alive"


def drones_present() -> str:
    return f"{ROOT}/*/alive"


def uav_of_presence(key: str) -> str:
    """The drone id in a presence token's key (`dynqos/<uav>/alive`), unchecked."""
    return key.split("/")[1] if key.count("/") == 2 else ""


def replicas_of(service: str, group: str = "all") -> str:
    """The liveliness tokens of the replicas of an edge service that share one set of drones (`group`:
    all of them, or one static shard); "edge" is never a drone id."""
    return f"{ROOT}/edge/replicas/{service}/{group}/*"


def replica_token(service: str, group: str, replica: str) -> str:
    return f"{ROOT}/edge/replicas/{service}/{group}/{replica}"


def replica_beat(service: str, group: str, replica: str) -> str:
    """A replica's heartbeat (an empty put every few ms from its loop): a token says a process lives;
    its beats say its loop still turns (edge/replicas.py, `beats`)."""
    return f"{ROOT}/edge/beats/{service}/{group}/{replica}"


def state_watch(service: str, group: str, uav: str) -> str:
    """Where the replica flying a drone puts a few of the drone's States a second for the replica
    standing by for it (edge/mpc/service.py): the standby follows the drone's term without receiving
    each of its states. Under the drone's id, so a receiver checks the State is that drone's; no drone
    may read or write it (common/acl.py)."""
    return f"{ROOT}/{check_uav_id(uav)}/watch/{service}/{group}"


def any_state_watch(service: str) -> str:
    """Every drone's watch key of an edge service, in any group (what its ACL rules cover)."""
    return f"{ROOT}/*/watch/{service}/**"


def is_state_watch(key: str) -> bool:
    """Whether `key` is a watch key (a replica's copy), not the drone's own uplink."""
    return key.split("/", 3)[2:3] == ["watch"]


def any_replica_beat(service: str) -> str:
    """Every heartbeat of an edge service's replicas, in any group (what its ACL rules cover)."""
    return f"{ROOT}/edge/beats/{service}/**"


def any_replica_of(service: str) -> str:
    """Every token of an edge service's replicas, in any group (what its ACL rules cover)."""
    return f"{ROOT}/edge/replicas/{service}/**"


def qos_active(group: str, replica: str) -> str:
    """The token of the QoS agent that is active (edge/qos/leadership.py); one chunk deeper than the
    members' tokens, so `replicas_of("qos", group)` does not match it."""
    return f"{ROOT}/edge/replicas/qos/{group}/active/{replica}"


def qos_actives(group: str) -> str:
    return f"{ROOT}/edge/replicas/qos/{group}/active/*"


def replica_of_token(key: str) -> str:
    """The replica id at the end of a replica token's key."""
    return key.rsplit("/", 1)[-1]


@dataclass(frozen=True, slots=True)
class UplinkKey:
    uav: str
    flow: Flow
    stream: Stream


@dataclass(frozen=True, slots=True)
class DownlinkKey:
    uav: str
    kind: Downlink


_STREAMS = {s.value: s for s in Stream}
_FLOWS = {f.value: f for f in Flow}
_DOWNLINKS = {d.value: d for d in Downlink}


def parse(key: str) -> UplinkKey | DownlinkKey:
    """Parse a concrete (wildcard-free) dynqos key; raise KeyExprError naming what is wrong."""
    if not isinstance(key, str):
        raise KeyExprError(f"key must be a string, got {type(key).__name__}")
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyExprError(f"key {key[:80]!r} is not a dynqos key (expected '{ROOT}/<uav>/...')")
    uav = check_uav_id(parts[1])
    rest = parts[2:]
    if rest[0] == "up":
        if len(rest) < 3:
            raise KeyExprError(f"key {key!r}: uplink key needs a flow and a stream")
        flow = _FLOWS.get(rest[1])
        if flow is None:
            raise KeyExprError(f"key {key!r}: unknown flow {rest[1]!r} (expected default or priority)")
        stream = _STREAMS.get("/".join(rest[2:]))
        if stream is None:
            raise KeyExprError(f"key {key!r}: unknown stream {'/'.join(rest[2:])!r}")
        return UplinkKey(uav, flow, stream)
    kind = _DOWNLINKS.get("/".join(rest))
    if kind is None:
        raise KeyExprError(f"key {key!r}: unknown key kind {'/'.join(rest)!r}")
    return DownlinkKey(uav, kind)
