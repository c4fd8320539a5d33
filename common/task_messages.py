"""A user's offloaded task on the wire (docs/offload.md): the drone's request and the edge's answer.

The user's own request and answer travel as `body`, encoded by the task's codec (common/tasks.py), so
these two envelopes are all the wire knows of any task: the runtime checks them like every message
(registered and coded in common/messages.py), and the task's codec checks the body against the task's
own types. The request carries its budget, not an absolute deadline: the two sides share no clock
(docs/architecture.md), so the edge counts the budget from the request's arrival and drops work that
waited past it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from dynqos.common import fields as f
from dynqos.common.message_base import COMMON, LATENCY_MS, MAX_PAYLOAD_BYTES, Message

TASK_NAME_MAX = 32


@dataclass(frozen=True, slots=True, kw_only=True)
class TaskRequest(Message):
    """The drone to a task's edge service: one call, numbered by `seq` (increasing per drone and task)."""

    TYPE: ClassVar[str] = "TaskRequest"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "task": f.text(TASK_NAME_MAX),
        "stamp_ns": f.integer(),
        "budget_ms": LATENCY_MS,
        "body": f.blob(MAX_PAYLOAD_BYTES),
    }

    task: str
    stamp_ns: int  # the drone's clock when it sent the request (echoed in the answer)
    budget_ms: float  # the task's deadline: an answer later than this is of no use to the drone
    body: bytes


@dataclass(frozen=True, slots=True, kw_only=True)
class TaskAnswer(Message):
    """A task's edge service to the drone: the answer to request `seq`."""

    TYPE: ClassVar[str] = "TaskAnswer"
    SCHEMA: ClassVar[dict[str, f.Validator]] = {
        **COMMON,
        "task": f.text(TASK_NAME_MAX),
        "stamp_ns": f.integer(),
        "handle_ms": LATENCY_MS,
        "replica": f.text(64),
        "body": f.blob(MAX_PAYLOAD_BYTES),
    }

    task: str
    stamp_ns: int  # the request's, as it came
    handle_ms: float  # how long the user's handler took
    replica: str
    body: bytes
