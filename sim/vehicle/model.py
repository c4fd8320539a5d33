"""The simulated vehicle: plant + flight controller stepped together at a fixed rate. Pure.

This is the lock-step core: `advance(seconds)` is deterministic for a given seed and input sequence,
and runs as fast as the CPU allows. The MAVLink shell (`sim/vehicle/mavlink.py`) drives it in real time.

What the vehicle reports is an estimate, as a flight controller's is: the true position plus a slow
horizontal wander (`[vehicle] position_noise_m`, a first-order process with `position_noise_tau_s`),
the size PX4's estimator showed at rest in SIH (4 cm RMS). The physics and the world's contacts use
the true state.
"""

from __future__ import annotations

import numpy as np

from dynqos.common.clock import NS_PER_S
from dynqos.common.config import VehicleSimConfig
from dynqos.sim.vehicle.dynamics import GaussMarkov, QuadParams, Quadrotor, QuadState, Vec, Wind
from dynqos.sim.vehicle.px4 import FlightController

PHYSICS_HZ = 200
STEP_NS = NS_PER_S // PHYSICS_HZ


class VehicleModel:
    """The world and the FC's settings are `[vehicle]`; the airframe is `params` (not a setting)."""

    def __init__(self, config: VehicleSimConfig | None = None, params: QuadParams | None = None) -> None:
        self.config = cfg = config or VehicleSimConfig()
        self.params = params or QuadParams()
        wind = Wind(cfg.wind_mps, gust_std_mps=cfg.gust_std_mps, gust_tau_s=cfg.gust_tau_s, seed=cfg.seed)
        self.plant = Quadrotor(self.params, wind)
        self.plant.state.pos_m[:2] = cfg.start_m  # on the ground where it was spawned
        self.fc = FlightController(
            self.params,
            offboard_loss_s=self.config.offboard_loss_s,
            takeoff_alt_m=self.config.takeoff_alt_m,
        )
        self.now_ns = 0
        self._wander = GaussMarkov(cfg.position_noise_m, cfg.position_noise_tau_s, cfg.seed + 1, axes=2)

    @property
    def state(self) -> QuadState:
        return self.plant.state

    def reported_position(self) -> Vec:
        """Where the vehicle says it is (its estimate), in local NED."""
        north, east = self._wander.value
        reported: Vec = self.plant.state.pos_m + np.array([north, east, 0.0])
        return reported

    def step(self) -> QuadState:
        """One physics step (1/200 s)."""
        thrust, torque = self.fc.update(self.plant.state, self.plant.on_ground, self.now_ns)
        self.plant.step(thrust, torque, STEP_NS / NS_PER_S)
        self._wander.step(STEP_NS / NS_PER_S)
        self.now_ns += STEP_NS
        return self.plant.state

    def advance(self, seconds: float) -> QuadState:
        for _ in range(round(seconds * PHYSICS_HZ)):
            self.step()
        return self.plant.state
