"""What the flight controller reports and what it is sent, as plain values. Pure.

The MAVLink link (onboard/fclink.py) fills these in and sends them; the onboard core decides with them
and never sees MAVLink. Frame: local NED, metres, seconds, radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynqos.common.clock import to_ns
from dynqos.common.geometry import yaw_of


@dataclass(frozen=True, slots=True)
class FcState:
    """The FC's latest position, velocity and attitude, stamped on arrival with the onboard clock."""

    stamp_ns: int
    pos_m: tuple[float, float, float]
    vel_mps: tuple[float, float, float]
    quat: tuple[float, float, float, float]  # w, x, y, z


FC_SAID_FRESH_S = 10.0  # the FC's last words ride in the status this long after they came


@dataclass(frozen=True, slots=True)
class FcSaid:
    """What the FC said last (a STATUSTEXT, or a PX4 event described), its MAV_SEVERITY (0 emergency ..
    7 debug) and when it arrived (onboard clock)."""

    text: str
    severity: int
    stamp_ns: int

    def fresh(self, now_ns: int) -> bool:
        """Recent enough to ride in the drone's status (FC_SAID_FRESH_S after it came)."""
        return now_ns - self.stamp_ns <= to_ns(FC_SAID_FRESH_S)


@dataclass(frozen=True, slots=True)
class AccelSetpoint:
    """Fly this acceleration (the edge's horizon setpoint, or the fallback PID's) and turn to this yaw."""

    accel_mps2: tuple[float, float, float]
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class PositionSetpoint:
    """Hold this position and yaw with the FC's own controller (the drone cannot trust its state)."""

    pos_m: tuple[float, float, float]
    yaw_rad: float


Setpoint = AccelSetpoint | PositionSetpoint


def hold_at(fc: FcState) -> PositionSetpoint:
    """A position hold where the FC says the drone is, facing where it faces."""
    return PositionSetpoint(fc.pos_m, yaw_of(fc.quat))


@dataclass
class Hold:
    """Where the drone holds (the fallback's target, or the FC-silence hold)."""

    pos_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0

    def set(self, fc: FcState) -> None:
        hold = hold_at(fc)
        self.pos_m, self.yaw_rad = np.array(hold.pos_m), hold.yaw_rad


def triple(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
