"""The simulated vehicle: plant + flight controller stepped together at a fixed rate. Pure.

This is the lock-step core: `advance(seconds)` is deterministic for a given seed and input sequence,
and runs as fast as the CPU allows. The MAVLink shell (`sim/vehicle.py`) drives it in real time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from dynqos.sim.dynamics import QuadParams, Quadrotor, QuadState, Wind
from dynqos.sim.px4 import FlightController

PHYSICS_HZ = 200
STEP_NS = 1_000_000_000 // PHYSICS_HZ


@dataclass(frozen=True, slots=True, kw_only=True)
class VehicleConfig:
    params: QuadParams = field(default_factory=QuadParams)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std_mps: float = 0.0
    gust_tau_s: float = 2.0
    seed: int = 0
    offboard_loss_s: float = 1.0
    takeoff_alt_m: float = 2.5


class VehicleModel:
    def __init__(self, config: VehicleConfig | None = None) -> None:
        self.config = config or VehicleConfig()
        cfg = self.config
        wind = Wind(cfg.wind, gust_std_mps=cfg.gust_std_mps, gust_tau_s=cfg.gust_tau_s, seed=cfg.seed)
        self.plant = Quadrotor(self.config.params, wind)
        self.fc = FlightController(
            self.config.params,
            offboard_loss_s=self.config.offboard_loss_s,
            takeoff_alt_m=self.config.takeoff_alt_m,
        )
        self.now_ns = 0

    @property
    def state(self) -> QuadState:
        return self.plant.state

    def step(self) -> QuadState:
        """One physics step (1/200 s)."""
        thrust, torque = self.fc.update(self.plant.state, self.plant.on_ground, self.now_ns)
        self.plant.step(thrust, torque, STEP_NS / 1e9)
        self.now_ns += STEP_NS
        return self.plant.state

    def advance(self, seconds: float) -> QuadState:
        for _ in range(round(seconds * PHYSICS_HZ)):
            self.step()
        return self.plant.state
