"""The rmw_zenoh wire format (ROS 2 over Zenoh), as rmw_zenoh_cpp writes it, so that ROS 2 nodes see
dynqos topics with no bridge of their own (docs/ros2.md).

What a ROS 2 node needs before it takes a sample (rmw_zenoh `docs/design.md`,
`rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`, `attachment_helpers.cpp`, `qos.cpp`):
- the data key `<domain>/<topic without leading slash>/<pkg>::msg::dds_::<Type>_/RIHS01_<hex>`;
- a 33-byte attachment on every sample: int64 sequence number (from 1), int64 source timestamp (ns
  since the epoch), a length byte (16) and the publisher's 16-byte GID; rmw_zenoh's subscriber drops a
  sample without it;
- liveliness tokens `@ros2_lv/<domain>/<zid>/<nid>/<eid>/<NN|MP|MS>/<enclave>/<namespace>/<node>
  [/<topic>/<type>/<hash>/<qos>]`, every `/` inside a name written `%`: `ros2 node list` and
  `ros2 topic list` are built from them;
- the QoS field `rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:liv,lease_s,lease_ns`, each value left empty
  where it equals rmw_zenoh's default (reliable, volatile, keep last 42, infinite durations,
  automatic liveliness).
Pure: no zenoh here; the service (`edge/ros2/service.py`) declares what these build.
"""

from __future__ import annotations

import enum
import hashlib
import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
ATTACHMENT = struct.Struct("<qqB")  # sequence number, source timestamp (ns), GID length; then the GID
CDR_LE_HEADER = b"\x00\x01\x00\x00"  # CDR, little endian, no options: what rmw_zenoh writes

DEFAULT_DEPTH = 42  # rmw_zenoh's default history depth (qos.cpp)


class Reliability(enum.IntEnum):  # rmw_qos_reliability_policy_e
    RELIABLE = 1
    BEST_EFFORT = 2


class Durability(enum.IntEnum):  # rmw_qos_durability_policy_e
    TRANSIENT_LOCAL = 1
    VOLATILE = 2


class Entity(str, enum.Enum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS a ROS 2 endpoint declares (keep-last history, infinite deadline, lifespan and lease)."""

    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    depth: int = DEFAULT_DEPTH

    def token_field(self) -> str:
        """rmw_zenoh's `qos_to_keyexpr`: a value only where it differs from the default."""
        reliability = "" if self.reliability is Reliability.RELIABLE else str(int(self.reliability))
        durability = "" if self.durability is Durability.VOLATILE else str(int(self.durability))
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


def dds_type_name(ros_type: str) -> str:
    """`geometry_msgs/msg/PoseStamped` -> `geometry_msgs::msg::dds_::PoseStamped_`."""
    package, kind, name = _split_type(ros_type)
    return f"{package}::{kind}::dds_::{name}_"


def _split_type(ros_type: str) -> tuple[str, str, str]:
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts) or parts[1] != "msg":
        raise ValueError(f"{ros_type!r} is not a ROS 2 message type (package/msg/Name)")
    return parts[0], parts[1], parts[2]


def mangle(name: str) -> str:
    """A name inside one key chunk: every `/` written `%` (rmw_zenoh's `mangle_name`)."""
    return name.replace("/", "%")


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """The data key of `topic` (a fully qualified name, `/dynqos/uav1/pose`)."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


@dataclass(frozen=True, slots=True)
class Node:
    domain_id: int
    zid: str  # the zenoh session id, in hex
    node_id: int
    namespace: str  # "/" for none
    name: str
    enclave: str = "/"

    def _prefix(self, entity_id: int, entity: Entity) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{entity.value}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def token(self) -> str:
        """The node's own liveliness token (its entity id is its node id)."""
        return self._prefix(self.node_id, Entity.NODE)

    def endpoint_token(
        self, entity_id: int, entity: Entity, topic: str, ros_type: str, type_hash: str, qos: Qos
    ) -> str:
        return (
            f"{self._prefix(entity_id, entity)}/{mangle(topic)}/{dds_type_name(ros_type)}/"
            f"{type_hash}/{qos.token_field()}"
        )


def gid(token: str) -> bytes:
    """An endpoint's 16-byte GID, from its liveliness token as rmw_zenoh derives it (there with
    XXH3-128, here with BLAKE2b: receivers only compare GIDs, never recompute them)."""
    return hashlib.blake2b(token.encode(), digest_size=GID_BYTES).digest()


@dataclass(frozen=True, slots=True)
class Attachment:
    sequence: int  # from 1, per publisher
    source_ns: int  # wall clock, ns since the epoch
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_BYTES:
            raise ValueError(f"a GID is {GID_BYTES} bytes, not {len(self.gid)}")
        return ATTACHMENT.pack(self.sequence, self.source_ns, GID_BYTES) + self.gid

    @staticmethod
    def decode(data: bytes) -> Attachment:
        """What a ROS 2 publisher attached; ValueError for anything else (rmw_zenoh drops those)."""
        if len(data) != ATTACHMENT.size + GID_BYTES:
            raise ValueError(
                f"an rmw_zenoh attachment is {ATTACHMENT.size + GID_BYTES} bytes, not {len(data)}"
            )
        sequence, source_ns, length = ATTACHMENT.unpack_from(data)
        if length != GID_BYTES:
            raise ValueError(f"the attachment's GID length is {length}, not {GID_BYTES}")
        return Attachment(sequence, source_ns, bytes(data[ATTACHMENT.size :]))
