"""The paper's two offloaded services declared as tasks, on the API a user's task is declared on.

There is one way to offload (docs/offload.md): a `Task` says what crosses the link, how often, how late
an answer may come and which flow it rides. The MPC and the detector are declared here with their own
wire types (a State asks, a Command answers; a CameraFrame asks, Detections answer); their edge sides
are `Service`s (edge/mpc/service.py, edge/detector/service.py) that `dynqos edge serve` runs the way it
runs a user's. Their figures come from the config: what a deployment sets for the control step, the
watchdog and the camera is what the declaration says, on both sides.
"""

from __future__ import annotations

from dataclasses import replace

from dynqos.common.camera_messages import CameraFrame, Detections
from dynqos.common.config import Config
from dynqos.common.message_base import MAX_PAYLOAD_BYTES
from dynqos.common.messages import Command, State
from dynqos.common.tasks import Task

MPC = Task(
    "mpc",
    request=State,
    answer=Command,
    rate_hz=20.0,  # [control] t_mpc_s: a State each control step
    deadline_s=0.15,  # [supervisor] watchdog_s: later than this, the onboard PID flies
    flow="control",
    max_request_bytes=4096,
    max_answer_bytes=16384,  # a horizon of up to 200 steps
    stateless=False,  # warm starts per drone; replicas hand a drone over by lease and term (fencing)
)

DETECTOR = Task(
    "detector",
    request=CameraFrame,
    answer=Detections,
    rate_hz=15.0,  # [onboard] camera_fps
    deadline_s=1.0,  # [onboard] camera_feedback_timeout_s: without an ack this long the rate halves
    flow="bulk",
    max_request_bytes=MAX_PAYLOAD_BYTES,
    max_answer_bytes=65536,
    stateless=True,  # any replica may answer any frame; replicas share the drones
)


def mpc(config: Config) -> Task[State, Command]:
    """The MPC as this config flies it: its step and its watchdog."""
    return replace(MPC, rate_hz=1.0 / config.control.t_mpc_s, deadline_s=config.supervisor.watchdog_s)


def detector(config: Config) -> Task[CameraFrame, Detections]:
    """The detector as this config feeds it: the camera's rate and its feedback time-out."""
    rate = max(config.onboard.camera_fps, 0.1)  # 0 fps (no camera): the declaration's least rate
    return replace(DETECTOR, rate_hz=rate, deadline_s=config.onboard.camera_feedback_timeout_s)
