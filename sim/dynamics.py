"""Rigid-body quadrotor dynamics in local NED, integrated with RK4. Pure: time is passed in.

State: position, velocity, attitude quaternion (body FRD -> NED, w x y z), body rates, and the
lagged collective thrust and body torques (first-order motor lag). Inputs: commanded thrust and
torques, which the motors reach with time constant `motor_tau_s`. Linear drag acts on the velocity
relative to the air, so wind (with gusts from a seeded RNG) pushes the vehicle.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from dynqos.common.geometry import yaw_of as yaw_of  # re-exported for the simulator

GRAVITY = 9.81
Vec = NDArray[np.float64]


@dataclass(frozen=True, slots=True, kw_only=True)
class QuadParams:
    mass_kg: float = 1.5
    inertia: tuple[float, float, float] = (0.02, 0.02, 0.04)
    max_thrust_n: float = 2.2 * 1.5 * GRAVITY  # thrust-to-weight 2.2
    max_torque_nm: tuple[float, float, float] = (1.0, 1.0, 0.3)
    drag_per_s: tuple[float, float, float] = (0.25, 0.25, 0.4)  # linear drag / mass
    motor_tau_s: float = 0.02


@dataclass(slots=True)
class Wind:
    """Mean wind plus gusts: a first-order random process per axis (seeded)."""

    mean_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = 0.0
    gust_tau_s: float = 2.0
    seed: int = 0
    _gust: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    _rng: random.Random = field(init=False)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)

    def step(self, dt_s: float) -> Vec:
        if self.gust_std_mps > 0:
            a = math.exp(-dt_s / self.gust_tau_s)
            b = self.gust_std_mps * math.sqrt(1 - a * a)
            self._gust = [a * g + b * self._rng.gauss(0.0, 1.0) for g in self._gust]
        air: Vec = np.array(self.mean_mps) + np.array(self._gust)
        return air


def quat_to_rot(q: Vec) -> Vec:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(r: Vec) -> Vec:
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    out: Vec = np.array(q)
    out = out / np.linalg.norm(out) * (1 if out[0] >= 0 else -1)
    return out


@dataclass(slots=True)
class QuadState:
    pos_m: Vec = field(default_factory=lambda: np.zeros(3))
    vel_mps: Vec = field(default_factory=lambda: np.zeros(3))
    quat: Vec = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    rates_rps: Vec = field(default_factory=lambda: np.zeros(3))
    thrust_n: float = 0.0
    torque_nm: Vec = field(default_factory=lambda: np.zeros(3))

    def pack(self) -> Vec:
        return np.concatenate(
            [self.pos_m, self.vel_mps, self.quat, self.rates_rps, [self.thrust_n], self.torque_nm]
        )

    @classmethod
    def unpack(cls, x: Vec) -> QuadState:
        quat = x[6:10] / np.linalg.norm(x[6:10])
        return cls(x[0:3].copy(), x[3:6].copy(), quat, x[10:13].copy(), float(x[13]), x[14:17].copy())


class Quadrotor:
    """The plant. `step(thrust_cmd, torque_cmd, dt)` advances it by dt with RK4."""

    def __init__(self, params: QuadParams | None = None, wind: Wind | None = None) -> None:
        self.params = params or QuadParams()
        self.wind = wind or Wind()
        self.state = QuadState()
        self.on_ground = True
        self._inertia = np.array(self.params.inertia)
        self._drag = np.array(self.params.drag_per_s)
        self._max_torque = np.array(self.params.max_torque_nm)
        self._air = np.zeros(3)

    def _derivative(self, x: Vec, thrust_cmd: float, torque_cmd: Vec) -> Vec:
        p = self.params
        vel, quat, rates = x[3:6], x[6:10], x[10:13]
        thrust, torque = x[13], x[14:17]
        rot = quat_to_rot(quat / np.linalg.norm(quat))
        force = rot @ np.array([0.0, 0.0, -thrust])  # thrust along body -z
        accel = force / p.mass_kg + np.array([0.0, 0.0, GRAVITY]) - self._drag * (vel - self._air)
        w, qx, qy, qz = quat
        omega_q = np.array(
            [
                -qx * rates[0] - qy * rates[1] - qz * rates[2],
                w * rates[0] + qy * rates[2] - qz * rates[1],
                w * rates[1] - qx * rates[2] + qz * rates[0],
                w * rates[2] + qx * rates[1] - qy * rates[0],
            ]
        )
        rate_dot = (torque - np.cross(rates, self._inertia * rates)) / self._inertia
        thrust_dot = (thrust_cmd - thrust) / p.motor_tau_s
        torque_dot = (torque_cmd - torque) / p.motor_tau_s
        return np.concatenate([vel, accel, 0.5 * omega_q, rate_dot, [thrust_dot], torque_dot])

    def step(self, thrust_cmd: float, torque_cmd: Vec, dt_s: float) -> QuadState:
        p = self.params
        thrust_cmd = min(max(thrust_cmd, 0.0), p.max_thrust_n)
        torque_cmd = np.clip(torque_cmd, -self._max_torque, self._max_torque)
        self._air = self.wind.step(dt_s)
        x = self.state.pack()
        k1 = self._derivative(x, thrust_cmd, torque_cmd)
        k2 = self._derivative(x + 0.5 * dt_s * k1, thrust_cmd, torque_cmd)
        k3 = self._derivative(x + 0.5 * dt_s * k2, thrust_cmd, torque_cmd)
        k4 = self._derivative(x + dt_s * k3, thrust_cmd, torque_cmd)
        x = x + dt_s / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        state = QuadState.unpack(x)
        # The ground (z = 0 in NED) holds the vehicle up until thrust lifts it.
        if state.pos_m[2] >= 0.0:
            state.pos_m[2] = 0.0
            if state.vel_mps[2] > 0.0:
                state.vel_mps[:] = 0.0
                state.rates_rps[:] = 0.0
                yaw = yaw_of(state.quat)
                state.quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
            self.on_ground = True
        else:
            self.on_ground = False
        self.state = state
        return state
