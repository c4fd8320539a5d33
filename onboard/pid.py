"""The onboard fallback controller: cascaded PID, position -> velocity -> acceleration setpoint. Pure.

Saturation on velocity and acceleration, integrator anti-windup (conditional integration: the
integrator stops when the output saturates in the same direction), and bumpless hand-over:
`reset(current_accel)` starts the integrator where the edge's last acceleration command left off, so the
switch from edge to fallback does not jump.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class PidGains:
    pos_p: tuple[float, float, float] = (1.5, 1.5, 1.5)
    vel_p: tuple[float, float, float] = (3.5, 3.5, 4.0)
    vel_i: tuple[float, float, float] = (0.5, 0.5, 1.0)
    vel_max_mps: tuple[float, float, float] = (2.0, 2.0, 1.0)
    accel_max_mps2: tuple[float, float, float] = (6.0, 6.0, 4.0)


class CascadedPid:
    def __init__(self, gains: PidGains | None = None) -> None:
        self.gains = gains or PidGains()
        self._kp = np.array(self.gains.pos_p)
        self._kv = np.array(self.gains.vel_p)
        self._ki = np.array(self.gains.vel_i)
        self._vmax = np.array(self.gains.vel_max_mps)
        self._amax = np.array(self.gains.accel_max_mps2)
        self._integral = np.zeros(3)

    def reset(self, current_accel: Vec | None = None) -> None:
        """Bumpless start: the integral term alone reproduces `current_accel` at zero error."""
        self._integral = (
            np.zeros(3) if current_accel is None else np.clip(current_accel, -self._amax, self._amax)
        )

    def step(self, pos: Vec, vel: Vec, target_pos: Vec, dt_s: float, target_vel: Vec | None = None) -> Vec:
        vel_sp = self._kp * (target_pos - pos) + (target_vel if target_vel is not None else 0.0)
        vel_sp = np.clip(vel_sp, -self._vmax, self._vmax)
        error = vel_sp - vel
        candidate = self._integral + self._ki * error * dt_s
        raw = self._kv * error + candidate
        accel: Vec = np.clip(raw, -self._amax, self._amax)
        # Anti-windup: integrate only where the output is not saturated in the direction of the error.
        saturated = (raw != accel) & (np.sign(error) == np.sign(raw))
        self._integral = np.where(saturated, self._integral, candidate)
        return accel
