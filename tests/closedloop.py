"""An in-process closed loop: the simulator's vehicle, a delayed network, and the edge MPC.

States go up at 20 Hz with half the RTT of delay, commands come back with the other half; the drone
applies the horizon setpoint for its current time as an acceleration setpoint at 50 Hz, as the onboard
daemon does. Everything runs on the simulator's clock, so it is deterministic.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from dynqos.common.messages import Reference, State
from dynqos.edge.missions import Mission
from dynqos.edge.mpc import ControllerSettings, DroneController, Plan
from dynqos.sim.px4 import MAIN_OFFBOARD, Setpoint
from dynqos.sim.vehicle_model import VehicleModel

STATE_NS = 50_000_000
SETPOINT_NS = 20_000_000


def fly_circle(
    rtt_ms: float, settings: ControllerSettings, seconds: float = 25.0, mission: Mission | None = None
) -> tuple[float, list[Plan]]:
    """RMSE (m) of position against the mission after the first lap (10 s), and every plan sent."""
    mission = mission or Mission(kind="circle", lead_in_s=0.0, radius_m=2.0, period_s=10.0)
    model = VehicleModel()
    fc = model.fc
    fc.arm(True, model.state, True, 0)
    fc.takeoff(1.5, model.state, 0)
    model.advance(6.0)
    for _ in range(5):
        fc.on_setpoint(Setpoint(pos_m=(0.0, 0.0, -1.5)), model.now_ns)
        model.advance(0.02)
    fc.set_mode(MAIN_OFFBOARD, 0, model.state, model.now_ns)
    ctrl = DroneController("uav1", settings)
    t0 = model.now_ns
    half_ns = round(rtt_ms * 1e6 / 2)
    uplink: deque[tuple[int, State]] = deque()
    downlink: deque[tuple[int, Plan]] = deque()
    active: Plan | None = None
    plans: list[Plan] = []
    errors = []
    seq = 0
    while model.now_ns - t0 < seconds * 1e9:
        now = model.now_ns
        if (now - t0) % STATE_NS == 0:
            s = model.state
            seq += 1
            uplink.append(
                (
                    now + half_ns,
                    State(
                        uav="uav1",
                        seq=seq,
                        stamp_ns=now,
                        pos_m=tuple(s.pos_m),
                        vel_mps=tuple(s.vel_mps),
                        quat=tuple(s.quat),
                        rtt_est_ms=rtt_ms,
                    ),
                )
            )
            if seq % 2 == 1:  # the planner's reference, every 100 ms
                pos, vel, yaw = mission.samples((now - t0) / 1e9, 0.05, 60)
                ctrl.reference.update(
                    Reference(
                        uav="uav1", seq=seq, stamp_ns=now, dt_s=0.05, pos_m=pos, vel_mps=vel, yaw_rad=yaw
                    ),
                    now,
                )
        while uplink and uplink[0][0] <= now:
            _, state = uplink.popleft()
            plan = ctrl.step(state, now)
            assert plan is not None
            plans.append(plan)
            downlink.append((now + half_ns, plan))
        while downlink and downlink[0][0] <= now:
            _, active = downlink.popleft()
        if active is not None and (now - t0) % SETPOINT_NS == 0:
            k = min((now - active.state_stamp_ns) // STATE_NS, len(active.accel_mps2) - 1)
            fc.on_setpoint(Setpoint(accel_mps2=active.accel_mps2[k], yaw_rad=active.yaw_rad[k]), now)
        model.step()
        t = (model.now_ns - t0) / 1e9
        if t > 10.0:
            p, _, _ = mission.sample(t)
            errors.append(float(np.linalg.norm(model.state.pos_m - np.array(p))))
    return float(np.sqrt(np.mean(np.square(errors)))), plans
