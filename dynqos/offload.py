"""Offload your own work: the one module a user's task imports (docs/offload.md).

    from dynqos.offload import Drone, Edge, Onboard, Steer, Task

    TASK = Task("look-at", request=Where, answer=Heading, rate_hz=10, deadline_s=0.1, flow="control")
    EDGE = Edge(TASK, handle=look)                                 # dynqos edge serve my_task:EDGE
    ONBOARD = Onboard(TASK, request=ask, apply=turn, fallback=hold)  # [onboard] tasks = ["my_task:ONBOARD"]

Everything else in dynqos is the runtime's own and may change between releases; these names do not.
"""

from dynqos.common.tasks import Drone, Edge, Onboard, PayloadError, Service, Steer, Task, TaskError

__all__ = ["Drone", "Edge", "Onboard", "PayloadError", "Service", "Steer", "Task", "TaskError"]
