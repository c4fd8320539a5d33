"""What the flight controller reports and what it is sent, as plain values. Pure.

The MAVLink link (onboard/fclink.py) fills these in and sends them; the onboard core decides with them
and never sees MAVLink. Frame: local NED, metres, seconds, radians.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FcState:
    """The FC's latest position, velocity and attitude, stamped on arrival with the onboard clock."""

    stamp_ns: int
    pos_m: tuple[float, float, float]
    vel_mps: tuple[float, float, float]
    quat: tuple[float, float, float, float]  # w, x, y, z


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
