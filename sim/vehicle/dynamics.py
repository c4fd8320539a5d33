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
    """PX4 SIH's quadrotor (its SIH_* defaults): flown side by side with PX4, a vehicle with a quarter
    of SIH's drag turned the MPC's accelerations into 87% of the velocity where PX4 gave 58%, and the
    demo's figures followed the airframe, not the loop (docs/simulator.md, "Against PX4 itself")."""

    mass_kg: float = 1.0  # SIH_MASS
    inertia: tuple[float, float, float] = (0.025, 0.025, 0.030)  # SIH_IXX, SIH_IYY, SIH_IZZ
    max_thrust_n: float = 4 * 5.0  # four SIH_T_MAX: thrust-to-weight 2.04
    max_torque_nm: tuple[float, float, float] = (1.0, 1.0, 0.3)
    drag_per_s: tuple[float, float, float] = (1.0, 1.0, 1.0)  # SIH_KDV / SIH_MASS
    motor_tau_s: float = 0.02  # SIH_T_TAU is 0.05: our attitude loop (not PX4s) needs faster motors


class GaussMarkov:
    """A first-order random process per axis (seeded): the wind's gusts, the estimator's wander."""

    def __init__(self, std: float, tau_s: float, seed: int, axes: int = 3) -> None:
        self.std, self.tau_s = std, tau_s
        self._rng = random.Random(seed)
        self.value = [0.0] * axes

    def step(self, dt_s: float) -> list[float]:
        if self.std > 0:
            a = math.exp(-dt_s / self.tau_s)
            b = self.std * math.sqrt(1 - a * a)
            self.value = [a * v + b * self._rng.gauss(0.0, 1.0) for v in self.value]
        return self.value


@dataclass(slots=True)
class Wind:
    """Mean wind plus gusts (seeded)."""

    mean_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = 0.0
    gust_tau_s: float = 2.0
    seed: int = 0
    _gust: GaussMarkov = field(init=False)

    def __post_init__(self) -> None:
        self._gust = GaussMarkov(self.gust_std_mps, self.gust_tau_s, self.seed)

    def step(self, dt_s: float) -> tuple[float, float, float]:
        m, g = self.mean_mps, self._gust.step(dt_s)
        return (m[0] + g[0], m[1] + g[1], m[2] + g[2])


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
        self._inertia = self.params.inertia
        self._drag = self.params.drag_per_s
        self._air: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def _derivative(self, x: list[float], thrust_cmd: float, torque_cmd: tuple[float, ...]) -> list[float]:
        """dx/dt on plain floats: numpy's per-call overhead on 3-vectors was most of a simulator's CPU,
        and a fleet runs one simulator per drone."""
        p = self.params
        vx, vy, vz, w, qx, qy, qz, r0, r1, r2, thrust, t0, t1, t2 = x[3:17]
        norm = math.sqrt(w * w + qx * qx + qy * qy + qz * qz)
        nw, nx, ny, nz = w / norm, qx / norm, qy / norm, qz / norm
        # thrust along body -z: the third column of the rotation, times -thrust
        col = (2 * (nx * nz + nw * ny), 2 * (ny * nz - nw * nx), 1 - 2 * (nx * nx + ny * ny))
        air, drag, inertia, tau = self._air, self._drag, self._inertia, p.motor_tau_s
        ax = -thrust * col[0] / p.mass_kg - drag[0] * (vx - air[0])
        ay = -thrust * col[1] / p.mass_kg - drag[1] * (vy - air[1])
        az = -thrust * col[2] / p.mass_kg + GRAVITY - drag[2] * (vz - air[2])
        i0, i1, i2 = inertia[0] * r0, inertia[1] * r1, inertia[2] * r2  # rates x (I rates): gyroscopic
        return [
            vx,
            vy,
            vz,
            ax,
            ay,
            az,
            0.5 * (-qx * r0 - qy * r1 - qz * r2),
            0.5 * (w * r0 + qy * r2 - qz * r1),
            0.5 * (w * r1 - qx * r2 + qz * r0),
            0.5 * (w * r2 + qx * r1 - qy * r0),
            (t0 - (r1 * i2 - r2 * i1)) / inertia[0],
            (t1 - (r2 * i0 - r0 * i2)) / inertia[1],
            (t2 - (r0 * i1 - r1 * i0)) / inertia[2],
            (thrust_cmd - thrust) / tau,
            (torque_cmd[0] - t0) / tau,
            (torque_cmd[1] - t1) / tau,
            (torque_cmd[2] - t2) / tau,
        ]

    def step(self, thrust_cmd: float, torque_cmd: Vec, dt_s: float) -> QuadState:
        p = self.params
        thrust_cmd = min(max(thrust_cmd, 0.0), p.max_thrust_n)
        torque = tuple(
            min(max(float(t), -m), m) for t, m in zip(torque_cmd, self.params.max_torque_nm, strict=True)
        )
        self._air = self.wind.step(dt_s)
        x = self.state.pack().tolist()
        half = 0.5 * dt_s
        k1 = self._derivative(x, thrust_cmd, torque)
        k2 = self._derivative([a + half * b for a, b in zip(x, k1, strict=True)], thrust_cmd, torque)
        k3 = self._derivative([a + half * b for a, b in zip(x, k2, strict=True)], thrust_cmd, torque)
        k4 = self._derivative([a + dt_s * b for a, b in zip(x, k3, strict=True)], thrust_cmd, torque)
        sixth = dt_s / 6.0
        x = [
            a + sixth * (b1 + 2 * b2 + 2 * b3 + b4)
            for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4, strict=True)
        ]
        state = QuadState.unpack(np.array(x))
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
