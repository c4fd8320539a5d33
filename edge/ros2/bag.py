"""A flight log ROS 2 tools open: an MCAP with the ROS 2 message encoding, as `ros2 bag record -s mcap`
writes it (`ros2msg` schemas with their dependencies, `cdr` messages, the `ros2` profile), from the
samples `edge/ros2/translate.py` makes (docs/ros2.md, `dynqos record --ros2`).

The writer is the mcap project's own (`mcap`); the schema texts are rosbags' `generate_msgdef`, the
concatenated definitions that rosbag2's MCAP storage writes; each channel carries the publisher's QoS
the way rosbag2 records it (`offered_qos_profiles`, YAML).
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

from mcap.writer import Writer

from dynqos.common.errors import DynqosError
from dynqos.edge.ros2.codec import STORE
from dynqos.edge.ros2.translate import RosSample
from dynqos.edge.ros2.wire import Qos


def qos_yaml(qos: Qos) -> str:
    """rosbag2's `offered_qos_profiles` for one publisher (history 1 = keep last; durability 2 =
    volatile; liveliness 1 = automatic; durations infinite)."""
    infinite = "\n    sec: 9223372036\n    nsec: 854775807"
    return (
        f"- history: 1\n  depth: {qos.depth}\n  reliability: {int(qos.reliability)}\n"
        f"  durability: {int(qos.durability)}\n  deadline:{infinite}\n  lifespan:{infinite}\n"
        f"  liveliness: 1\n  liveliness_lease_duration:{infinite}\n  avoid_ros_namespace_conventions: false"
    )


class Ros2Mcap:
    def __init__(self, path: Path, library: str = "dynqos") -> None:
        if path.suffix != ".mcap":
            raise DynqosError(f"--out {path}: an MCAP file name ends in .mcap")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file: BinaryIO = path.open("wb")
        except OSError as exc:
            raise DynqosError(f"cannot write {path}: {exc.strerror or exc}") from None
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library=library)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self.written = 0

    def _channel(self, sample: RosSample) -> int:
        channel = self._channels.get(sample.topic)
        if channel is not None:
            return channel
        schema = self._schemas.get(sample.ros_type)
        if schema is None:
            text, _ = STORE.generate_msgdef(sample.ros_type, ros_version=2)
            schema = self._writer.register_schema(sample.ros_type, "ros2msg", text.encode())
            self._schemas[sample.ros_type] = schema
        channel = self._writer.register_channel(
            sample.topic, "cdr", schema, metadata={"offered_qos_profiles": qos_yaml(sample.qos)}
        )
        self._channels[sample.topic] = channel
        return channel

    def write(self, sample: RosSample, log_time_ns: int) -> None:
        channel = self._channel(sample)
        sequence = self._sequence.get(channel, 0) + 1
        self._sequence[channel] = sequence
        self._writer.add_message(channel, log_time_ns, sample.payload, log_time_ns, sequence)
        self.written += 1

    def close(self) -> None:
        """The summary and footer: a complete file."""
        self._writer.finish()  # type: ignore[no-untyped-call]
        self._file.close()
