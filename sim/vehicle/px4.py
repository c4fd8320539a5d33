"""A PX4-like flight controller for the simulated quadrotor. Pure: time is passed in.

What it emulates, because the onboard daemon must also fly a real PX4:
- arming and disarming, takeoff, hold (AUTO.LOITER), land, offboard mode with PX4's custom mode
  encoding (main mode in bits 16-23, sub mode in bits 24-31 of custom_mode);
- offboard rules: switching to offboard is refused unless setpoints are streaming, and when setpoints
  stop for `offboard_loss_s` (COM_OF_LOSS_T, 1 s) the vehicle holds position (AUTO.LOITER);
- the cascade position -> velocity -> acceleration -> attitude/thrust -> body torques, accepting
  position, velocity and acceleration setpoints (and yaw) as SET_POSITION_TARGET_LOCAL_NED's type_mask
  selects them.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from dynqos.sim.vehicle.dynamics import GRAVITY, QuadParams, QuadState, Vec, yaw_of

# PX4 custom modes (px4_custom_mode.h)
MAIN_MANUAL, MAIN_POSCTL, MAIN_AUTO, MAIN_OFFBOARD = 1, 3, 4, 6
SUB_AUTO_READY, SUB_AUTO_TAKEOFF, SUB_AUTO_LOITER, SUB_AUTO_LAND = 1, 2, 3, 6

# POSITION_TARGET_TYPEMASK bits
IGNORE_POSITION = 0b000000111
IGNORE_VELOCITY = 0b000111000
IGNORE_ACCEL = 0b111000000
IGNORE_YAW = 1024


class Mode(enum.Enum):
    MANUAL = (MAIN_MANUAL, 0)
    POSCTL = (MAIN_POSCTL, 0)
    AUTO_READY = (MAIN_AUTO, SUB_AUTO_READY)
    TAKEOFF = (MAIN_AUTO, SUB_AUTO_TAKEOFF)
    HOLD = (MAIN_AUTO, SUB_AUTO_LOITER)
    LAND = (MAIN_AUTO, SUB_AUTO_LAND)
    OFFBOARD = (MAIN_OFFBOARD, 0)

    @property
    def custom_mode(self) -> int:
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @classmethod
    def from_custom(cls, main: int, sub: int) -> Mode | None:
        for mode in cls:
            mode_main, mode_sub = mode.value
            if mode_main == main and (main != MAIN_AUTO or mode_sub == sub):
                return mode
        return None


class Result(enum.IntEnum):
    """MAV_RESULT values."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


@dataclass(frozen=True, slots=True)
class Setpoint:
    """A SET_POSITION_TARGET_LOCAL_NED in NED; None where type_mask ignores the field."""

    pos_m: tuple[float, float, float] | None = None
    vel_mps: tuple[float, float, float] | None = None
    accel_mps2: tuple[float, float, float] | None = None
    yaw_rad: float | None = None

    @classmethod
    def from_mavlink(
        cls,
        type_mask: int,
        pos: tuple[float, float, float],
        vel: tuple[float, float, float],
        accel: tuple[float, float, float],
        yaw: float,
    ) -> Setpoint | None:
        """None when the setpoint is unusable (nothing set, or a non-finite value)."""

        def pick(values: tuple[float, float, float], ignore: int) -> tuple[float, float, float] | None:
            if type_mask & ignore == ignore:
                return None
            if not all(math.isfinite(v) for v in values):
                raise ValueError("non-finite setpoint")
            return values

        try:
            sp = cls(
                pick(pos, IGNORE_POSITION),
                pick(vel, IGNORE_VELOCITY),
                pick(accel, IGNORE_ACCEL),
                None if type_mask & IGNORE_YAW or not math.isfinite(yaw) else yaw,
            )
        except ValueError:
            return None
        if sp.pos_m is None and sp.vel_mps is None and sp.accel_mps2 is None:
            return None
        return sp


@dataclass(frozen=True, slots=True, kw_only=True)
class ControllerGains:
    pos_p: tuple[float, float, float] = (0.95, 0.95, 1.0)  # MPC_XY_P, MPC_Z_P
    vel_p: tuple[float, float, float] = (1.8, 1.8, 4.0)  # MPC_XY_VEL_P_ACC, MPC_Z_VEL_P_ACC
    vel_i: tuple[float, float, float] = (0.4, 0.4, 2.0)
    vel_max_mps: tuple[float, float, float] = (12.0, 12.0, 3.0)
    accel_max_mps2: float = 10.0
    tilt_max_rad: float = math.radians(35.0)
    att_wn: float = 25.0
    att_zeta: float = 0.8
    yaw_wn: float = 8.0


class FlightController:
    """PX4-like modes and cascade. Call `update(state, now_ns)` each physics step."""

    def __init__(
        self,
        params: QuadParams | None = None,
        gains: ControllerGains | None = None,
        *,
        offboard_loss_s: float = 1.0,
        takeoff_alt_m: float = 2.5,
    ) -> None:
        self.params = params or QuadParams()
        self.gains = gains or ControllerGains()
        self.offboard_loss_ns = round(offboard_loss_s * 1e9)
        self.default_takeoff_alt_m = takeoff_alt_m
        self.armed = False
        self.mode = Mode.POSCTL
        self.setpoint: Setpoint | None = None
        self.setpoint_ns: int | None = None
        self._setpoint_times: list[int] = []
        self.hold_pos: Vec | None = None
        self.hold_yaw = 0.0
        self.takeoff_target_z = -takeoff_alt_m
        self._vel_integral = np.zeros(3)
        self.failsafe_events = 0
        self.events: list[str] = []  # what happened, for the I/O shell to log and the tests to check

    # ---- commands ----------------------------------------------------------------------------------

    def arm(self, arm: bool, state: QuadState, on_ground: bool, now_ns: int) -> Result:
        if arm == self.armed:
            return Result.ACCEPTED
        if arm:
            self.armed = True
            self._hold_here(state)
            self.events.append("armed")
            return Result.ACCEPTED
        if not on_ground:
            return Result.DENIED  # PX4 refuses to disarm in flight without force
        self.armed = False
        self.mode = Mode.POSCTL if self.mode is Mode.OFFBOARD else self.mode
        self.events.append("disarmed")
        return Result.ACCEPTED

    def takeoff(self, altitude_m: float | None, state: QuadState, now_ns: int) -> Result:
        if not self.armed:
            return Result.DENIED
        alt = (
            self.default_takeoff_alt_m if altitude_m is None or not math.isfinite(altitude_m) else altitude_m
        )
        if not 0.5 <= alt <= 100.0:
            return Result.DENIED
        self.takeoff_target_z = -alt
        self.hold_pos = np.array([state.pos_m[0], state.pos_m[1], -alt])
        self.hold_yaw = yaw_of(state.quat)
        self.mode = Mode.TAKEOFF
        self.events.append(f"takeoff to {alt:.1f} m")
        return Result.ACCEPTED

    def land(self, state: QuadState) -> Result:
        if not self.armed:
            return Result.DENIED
        self.hold_pos = np.array([state.pos_m[0], state.pos_m[1], 0.0])
        self.mode = Mode.LAND
        self.events.append("landing")
        return Result.ACCEPTED

    def set_mode(self, main: int, sub: int, state: QuadState, now_ns: int) -> Result:
        mode = Mode.from_custom(main, sub)
        if mode is None:
            return Result.UNSUPPORTED
        if mode is self.mode:
            return Result.ACCEPTED
        if mode is Mode.OFFBOARD:
            if not self.setpoints_streaming(now_ns):
                self.events.append("offboard refused: no setpoint stream")
                return Result.TEMPORARILY_REJECTED
        elif mode is Mode.TAKEOFF:
            return self.takeoff(None, state, now_ns)
        elif mode is Mode.LAND:
            return self.land(state)
        elif mode in (Mode.HOLD, Mode.POSCTL, Mode.AUTO_READY):
            self._hold_here(state)
        self.mode = mode
        self.events.append(f"mode {mode.name}")
        return Result.ACCEPTED

    def on_setpoint(self, setpoint: Setpoint, now_ns: int) -> None:
        self.setpoint = setpoint
        self.setpoint_ns = now_ns
        self._setpoint_times = [t for t in self._setpoint_times if now_ns - t < 1_000_000_000][-50:]
        self._setpoint_times.append(now_ns)

    def setpoints_streaming(self, now_ns: int) -> bool:
        """PX4 wants a setpoint stream faster than 2 Hz before and during offboard."""
        recent = [t for t in self._setpoint_times if now_ns - t < 1_000_000_000]
        return len(recent) >= 3 and now_ns - recent[-1] < 500_000_000

    def _hold_here(self, state: QuadState) -> None:
        self.hold_pos = state.pos_m.copy()
        self.hold_yaw = yaw_of(state.quat)
        self._vel_integral[:] = 0.0

    # ---- control -----------------------------------------------------------------------------------

    def update(self, state: QuadState, on_ground: bool, now_ns: int) -> tuple[float, Vec]:
        """Thrust (N) and body torques (N m) for the motors."""
        lost = self.setpoint_ns is None or now_ns - self.setpoint_ns > self.offboard_loss_ns
        if self.mode is Mode.OFFBOARD and lost:
            self.failsafe_events += 1
            self._hold_here(state)
            self.mode = Mode.HOLD
            self.events.append("offboard lost: holding position")
        if not self.armed:
            return 0.0, np.zeros(3)
        if self.mode is Mode.TAKEOFF and state.pos_m[2] <= self.takeoff_target_z + 0.1:
            self.mode = Mode.HOLD
            self.events.append("takeoff complete: holding")
        if self.mode is Mode.LAND and on_ground:
            self.armed = False
            self.mode = Mode.AUTO_READY
            self.events.append("landed: disarmed")
            return 0.0, np.zeros(3)
        if self.mode is Mode.OFFBOARD and self.setpoint is not None:
            accel, yaw = self._offboard_accel(state)
        else:
            accel, yaw = self._hold_accel(state)
        return self._attitude(state, accel, yaw)

    def _velocity_to_accel(self, state: QuadState, vel_sp: Vec, dt_s: float = 0.005) -> Vec:
        g = self.gains
        vel_sp = np.clip(vel_sp, -np.array(g.vel_max_mps), np.array(g.vel_max_mps))
        error = vel_sp - state.vel_mps
        # The integral is an acceleration, at most 1 g as PX4 limits its own: against SIH's drag it
        # carries the whole push that holds 1 m/s (1 m/s^2).
        vel_i = np.array(g.vel_i)
        self._vel_integral = np.clip(self._vel_integral + vel_i * error * dt_s, -GRAVITY, GRAVITY)
        accel: Vec = np.array(g.vel_p) * error + self._vel_integral
        return accel

    def _hold_accel(self, state: QuadState) -> tuple[Vec, float]:
        target = self.hold_pos if self.hold_pos is not None else state.pos_m
        if self.mode is Mode.LAND:
            vel_sp = np.array(self.gains.pos_p) * (target - state.pos_m)
            vel_sp[2] = 0.7  # descend at 0.7 m/s
        else:
            vel_sp = np.array(self.gains.pos_p) * (target - state.pos_m)
        return self._velocity_to_accel(state, vel_sp), self.hold_yaw

    def _offboard_accel(self, state: QuadState) -> tuple[Vec, float]:
        sp = self.setpoint
        assert sp is not None
        accel = np.array(sp.accel_mps2) if sp.accel_mps2 is not None else np.zeros(3)
        if sp.pos_m is not None or sp.vel_mps is not None:
            vel_sp = np.array(sp.vel_mps) if sp.vel_mps is not None else np.zeros(3)
            if sp.pos_m is not None:
                vel_sp = vel_sp + np.array(self.gains.pos_p) * (np.array(sp.pos_m) - state.pos_m)
            accel = accel + self._velocity_to_accel(state, vel_sp)
        yaw = sp.yaw_rad if sp.yaw_rad is not None else yaw_of(state.quat)
        return accel, yaw

    def _attitude(self, state: QuadState, accel: Vec, yaw: float) -> tuple[float, Vec]:
        """Geometric attitude control (Lee et al. 2010) from an acceleration setpoint in NED.

        On plain floats: numpy's per-call overhead on 3-vectors made this a third of a simulator's CPU."""
        p, g = self.params, self.gains
        ax, ay, az = float(accel[0]), float(accel[1]), float(accel[2])
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if norm > g.accel_max_mps2:
            k = g.accel_max_mps2 / norm
            ax, ay, az = ax * k, ay * k, az * k
        m = p.mass_kg
        tx, ty, tz = m * ax, m * ay, m * (az - GRAVITY)  # the thrust vector points up (negative z) in hover
        tz = min(tz, -0.2 * m * GRAVITY)  # never ask for less than 20% of hover upward
        t_norm = math.sqrt(tx * tx + ty * ty + tz * tz)
        zx, zy, zz = -tx / t_norm, -ty / t_norm, -tz / t_norm  # body z (down) wanted
        tilt = math.acos(max(-1.0, min(1.0, zz)))
        if tilt > g.tilt_max_rad:  # limit tilt, keep the vertical component of thrust
            h = max(math.hypot(zx, zy), 1e-9)
            sin_max = math.sin(g.tilt_max_rad)
            zx, zy, zz = zx / h * sin_max, zy / h * sin_max, math.cos(g.tilt_max_rad)
        cx, cy = math.cos(yaw), math.sin(yaw)  # the course: body x wanted, before tilt (z = 0)
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx  # body y = z x course
        y_norm = max(math.sqrt(yx * yx + yy * yy + yz * yz), 1e-9)
        yx, yy, yz = yx / y_norm, yy / y_norm, yz / y_norm
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx  # body x = y x z
        r_des = ((xx, yx, zx), (xy, yy, zy), (xz, yz, zz))  # rows of the matrix with columns x, y, z
        w, qx, qy, qz = (float(v) for v in state.quat)
        rot = (
            (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy)),
            (2 * (qx * qy + w * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w * qx)),
            (2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx * qx + qy * qy)),
        )
        thrust = -(tx * rot[0][2] + ty * rot[1][2] + tz * rot[2][2])

        def rt_r(a: tuple[tuple[float, ...], ...], b: tuple[tuple[float, ...], ...], i: int, j: int) -> float:
            return a[0][i] * b[0][j] + a[1][i] * b[1][j] + a[2][i] * b[2][j]  # (a^T b)[i][j]

        # e_R = vee(R_des^T R - R^T R_des) / 2
        e_rot = (
            0.5 * (rt_r(r_des, rot, 2, 1) - rt_r(rot, r_des, 2, 1)),
            0.5 * (rt_r(r_des, rot, 0, 2) - rt_r(rot, r_des, 0, 2)),
            0.5 * (rt_r(r_des, rot, 1, 0) - rt_r(rot, r_des, 1, 0)),
        )
        inertia = p.inertia
        wn = (g.att_wn, g.att_wn, g.yaw_wn)
        r0, r1, r2 = (float(v) for v in state.rates_rps)
        i0, i1, i2 = inertia[0] * r0, inertia[1] * r1, inertia[2] * r2
        gyro = (r1 * i2 - r2 * i1, r2 * i0 - r0 * i2, r0 * i1 - r1 * i0)  # rates x (I rates)
        rates = (r0, r1, r2)
        torque = np.array(
            [
                -inertia[k] * wn[k] ** 2 * e_rot[k] - inertia[k] * 2 * g.att_zeta * wn[k] * rates[k] + gyro[k]
                for k in range(3)
            ]
        )
        return thrust, torque
