"""dynqos messages to ROS 2 samples: what `dynqos edge ros2` publishes and `dynqos record --ros2`
writes, decided in one place (docs/ros2.md). Pure: the caller gives the time to stamp with.

Per drone: every State gives `pose`, `odom` and a `/tf` transform; every SupervisorStatus a `status`
DiagnosticArray; every whole RGB JPEG (joined from its parts when paced) `camera/compressed` and
`camera/camera_info`; every Detections a vision_msgs `detections`; every QosGrant and QosDecision a
`qos` DiagnosticArray (the network's grant, the arbiter's decisions).
"""

from __future__ import annotations

from dataclasses import dataclass

from dynqos.common.messages import (
    CameraFrame,
    Detections,
    Message,
    QosDecision,
    QosGrant,
    State,
    SupervisorStatus,
)
from dynqos.edge.detector.assembler import FrameAssembler
from dynqos.edge.ros2 import codec
from dynqos.edge.ros2.wire import Qos, Reliability

POSE_QOS = Qos(Reliability.RELIABLE, depth=10)  # a pose is small and every one counts to a follower
STATUS_QOS = Qos(Reliability.RELIABLE, depth=10)
TF_QOS = Qos(Reliability.RELIABLE, depth=100)  # tf2's own listener default
CAMERA_QOS = Qos(Reliability.BEST_EFFORT, depth=1)  # ROS's sensor-data profile: the newest image only
DETECTIONS_QOS = Qos(Reliability.BEST_EFFORT, depth=10)  # per frame, as the detector keeps up: best effort
QOS_QOS = Qos(Reliability.RELIABLE, depth=10)  # each grant and decision counts
GRANT_LEVELS = {"available": 0, "requested": 1, "none": 1, "unavailable": 2}  # OK, WARN, ERROR
ADAPTING = ("q4", "q5", "q6")  # the supervisor adapts: a warning to a ROS monitor; qA (fallback): an error


@dataclass(frozen=True, slots=True)
class RosSample:
    topic: str  # fully qualified
    ros_type: str
    qos: Qos
    payload: bytes  # CDR


class Translator:
    def __init__(self, prefix: str, frame_id: str) -> None:
        self.prefix = prefix
        self.frame_id = frame_id
        self.assembler = FrameAssembler(max_frames=16, max_bytes=16 * 1024 * 1024)

    def translate(self, uav: str, message: Message, now_ns: int) -> list[RosSample]:
        """The ROS 2 samples of one message of `uav` (none for other kinds, or an image in parts)."""
        if isinstance(message, State):
            return self._state(uav, message, now_ns)
        if isinstance(message, SupervisorStatus):
            return [self._status(uav, message, now_ns)]
        if isinstance(message, CameraFrame):
            return self._image(uav, message, now_ns)
        if isinstance(message, Detections):
            payload = codec.detections(now_ns, f"{uav}/camera_optical", message.circles_px, message.centers_m)
            return [RosSample(f"/{self.prefix}/{uav}/detections", codec.DETECTIONS, DETECTIONS_QOS, payload)]
        if isinstance(message, QosGrant | QosDecision):
            return [self._qos(uav, message, now_ns)]
        return []

    def _state(self, uav: str, state: State, now: int) -> list[RosSample]:
        frame, body, base = self.frame_id, f"{uav}/base_link", f"/{self.prefix}/{uav}"
        return [
            RosSample(
                f"{base}/pose", codec.POSE, POSE_QOS, codec.pose_stamped(now, frame, state.pos_m, state.quat)
            ),
            RosSample(
                f"{base}/odom",
                codec.ODOMETRY,
                POSE_QOS,
                codec.odometry(now, frame, body, state.pos_m, state.vel_mps, state.quat),
            ),
            RosSample("/tf", codec.TF, TF_QOS, codec.transform(now, frame, body, state.pos_m, state.quat)),
        ]

    def _status(self, uav: str, status: SupervisorStatus, now: int) -> RosSample:
        state = status.state.value
        level = codec.ERROR if state == "qA" else codec.WARN if state in ADAPTING else codec.OK
        values = {
            "state": state,
            "flow": status.flow.value,
            "control": status.control_source.value,
            "risk": status.risk,
            "latency": status.latency,
            "camera_rate_factor": f"{status.camera_rate_factor:g}",
            "rtt_ms": _ms(status.rtt_ms),
            "camera_latency_ms": _ms(status.camera_latency_ms),
            "qos_grant": status.qos_grant.value,
            "depth_lost": str(status.depth_lost).lower(),
            "fc_said": status.fc_text,  # the flight controller's last words, while recent ("" none)
        }
        message = f"{state} on the {status.flow.value} flow, {status.control_source.value} flies"
        payload = codec.diagnostics(now, f"dynqos/{uav}/supervisor", uav, level, message, values)
        return RosSample(f"/{self.prefix}/{uav}/status", codec.DIAGNOSTICS, STATUS_QOS, payload)

    def _qos(self, uav: str, message: QosGrant | QosDecision, now: int) -> RosSample:
        if isinstance(message, QosGrant):
            grant = message.grant.value
            name, level = f"dynqos/{uav}/qos/grant", GRANT_LEVELS.get(grant, codec.WARN)
            text = f"priority flow {grant}" + (f": {message.reason}" if message.reason else "")
            values = {
                "grant": grant,
                "backend": message.backend,
                "session_id": message.session_id,
                "reason": message.reason,
            }
        else:
            name, level = f"dynqos/{uav}/qos/decision", codec.OK
            text = f"{message.action}: {message.reason}"
            values = {
                "action": message.action,
                "reason": message.reason,
                "risk": message.risk,
                "latency_excess": f"{message.latency_excess:g}",
                "holders": " ".join(message.holders),
            }
        payload = codec.diagnostics(now, name, uav, level, text, values)
        return RosSample(f"/{self.prefix}/{uav}/qos", codec.DIAGNOSTICS, QOS_QOS, payload)

    def _image(self, uav: str, frame: CameraFrame, now: int) -> list[RosSample]:
        whole = self.assembler.add(frame)
        if whole is None or whole.encoding != "jpeg":
            return []
        optical, base = f"{uav}/camera_optical", f"/{self.prefix}/{uav}/camera"
        return [
            RosSample(
                f"{base}/compressed",
                codec.COMPRESSED_IMAGE,
                CAMERA_QOS,
                codec.compressed_image(now, optical, "jpeg", whole.payload),
            ),
            RosSample(
                f"{base}/camera_info",
                codec.CAMERA_INFO,
                CAMERA_QOS,
                codec.camera_info(now, optical, whole.width, whole.height, whole.intrinsics),
            ),
        ]


def _ms(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"
