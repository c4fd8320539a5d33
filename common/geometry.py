"""Angles from attitudes, written once: the drone, the MPC and the simulator all read yaw this way."""

from __future__ import annotations

import math
from collections.abc import Iterable


def yaw_of(quat: Iterable[float]) -> float:
    """The yaw (rad, about NED's down axis) of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(q) for q in quat)
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
