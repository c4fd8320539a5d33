"""The drone's vocabulary: the supervisor's state, which flow a stream travels on, who flies the drone.

Each is defined once, here, and used by the messages, the supervisor, the onboard core, the
publishers and the report. They are `str` enums that behave as their plain value (in msgpack, CSV, f-strings
and as dict keys); a decoder turns an unknown value into a DecodeError, never into a new state.
"""

from __future__ import annotations

import enum


class Name(str, enum.Enum):
    """A str enum that is its value everywhere: in str(), f-strings, CSV, dict keys and msgpack."""

    def __str__(self) -> str:
        return str.__str__(self)

    def __hash__(self) -> int:
        return str.__hash__(self)


class SupervisorState(Name):
    """The states of the supervisor's PFSM (the paper's Table I)."""

    Q1 = "q1"  # offload, default flow
    Q2 = "q2"  # offload, priority flow (high risk, proactive)
    Q3 = "q3"  # offload, priority flow (medium risk and high latency)
    Q4 = "q4"  # offload, default flow, camera rate adaptation (low risk and high latency)
    Q5 = "q5"  # offload, priority flow, rate adaptation (high-risk context)
    Q6 = "q6"  # offload, priority flow, rate adaptation (medium/low-risk context)
    QA = "qA"  # full onboard autonomy: the fallback PID and the onboard planner


class Flow(Name):
    """A 5G QoS flow: a zenoh link with a priority range to its own router port."""

    DEFAULT = "default"
    PRIORITY = "priority"


class ControlSource(Name):
    """Who produces the setpoints the flight controller receives."""

    NONE = "none"  # not in offboard control: on the ground, or taking off
    EDGE = "edge"  # the edge MPC's horizon setpoint for now
    FALLBACK = "fallback"  # the onboard PID (the supervisor's qA, or the command watchdog)
    HOLD = "hold"  # the flight controller went silent: ask it to hold where it was last seen


class Grant(Name):
    """What the network has granted a drone's priority flow (the QoS agent's answer, docs/qos.md)."""

    NONE = "none"  # not asked for (or released)
    REQUESTED = "requested"  # asked; the network has not answered yet
    AVAILABLE = "available"  # the network prioritises the flow
    UNAVAILABLE = "unavailable"  # refused, ended by the network, or the API failed
