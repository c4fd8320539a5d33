"""An in-process closed loop: the real onboard core, the real MPC service and the simulator's vehicle.

The drone's OnboardCore and the edge's MpcService talk over a MemoryBus whose one-way delay is half
the RTT; the planner's Reference goes out on the same bus. Every part runs on the vehicle model's
clock, stepped at 200 Hz, with the core ticking at its 50 Hz setpoint rate and its setpoints applied
to the simulated flight controller: the same decisions as the daemon, deterministic and fast.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynqos.common import keys
from dynqos.common.bus import MemoryBus, Priority, Publisher, Received
from dynqos.common.clock import NS_PER_S
from dynqos.common.config import Config, MpcConfig, OnboardConfig
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Command, Reference
from dynqos.common.modes import ControlSource, Flow
from dynqos.common.queues import BoundedQueue
from dynqos.edge.mpc.batch import BatchSolver
from dynqos.edge.mpc.service import MpcService
from dynqos.edge.planner.missions import Mission
from dynqos.edge.runtime import Ports
from dynqos.onboard.core import SETPOINT_PERIOD_NS, OnboardCore
from dynqos.onboard.fc import AccelSetpoint, FcState
from dynqos.onboard.tick import TickInput
from dynqos.sim.vehicle.model import STEP_NS, VehicleModel
from dynqos.sim.vehicle.px4 import MAIN_OFFBOARD, Setpoint
from tests.edge_cores import turn

UAV = "uav1"
REFERENCE_NS = 100_000_000


class ModelClock:
    def __init__(self, model: VehicleModel) -> None:
        self.model = model

    def now_ns(self) -> int:
        return self.model.now_ns


@dataclass
class Flight:
    rmse_m: float
    commands: list[Command]
    sources: dict[ControlSource, int] = field(
        default_factory=dict
    )  # ticks flown by each, after the first lap
    core: OnboardCore | None = None
    service: MpcService | None = None


def fly_circle(
    rtt_ms: float,
    mpc: MpcConfig | None = None,
    seconds: float = 25.0,
    mission: Mission | None = None,
    qos: str = "priority",
    solver: BatchSolver | None = None,
) -> Flight:
    """Fly `mission` (a 2 m circle) through the loop; RMSE (m) against it after the first lap (10 s)."""
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

    config = Config(mpc=mpc or MpcConfig(), onboard=OnboardConfig(camera="none", qos=qos))  # type: ignore[arg-type]
    clock = ModelClock(model)
    one_way_ns = round(rtt_ms * 1e6 / 2)  # the drone's traffic crosses the network; the planner's does not
    bus = MemoryBus(clock, delays=[("dynqos/*/up/**", one_way_ns), ("dynqos/*/down/**", one_way_ns)])
    bus.declare_token(keys.drone_presence(UAV))  # as the drone's daemon does
    service = MpcService(config, Ports(bus, clock))
    if solver is not None:  # one that records what it solved
        service.solver = solver
    core = OnboardCore(config, start_ns=clock.now_ns())
    downlink: BoundedQueue[Received] = BoundedQueue(256)
    bus.subscribe(keys.downlink(UAV, Downlink.COMMAND), downlink, expect=(Command,))
    observed: BoundedQueue[Received] = BoundedQueue(100_000)
    bus.subscribe(keys.downlink(UAV, Downlink.COMMAND), observed, expect=(Command,))
    uplink: dict[tuple[Stream, Flow], Publisher] = {
        (stream, flow): bus.publisher(keys.uplink(UAV, flow, stream), Priority.DATA)
        for stream in Stream
        for flow in Flow
    }
    planner = bus.publisher(keys.downlink(UAV, Downlink.REFERENCE), Priority.DATA)

    t0 = model.now_ns
    errors = []
    sources: dict[ControlSource, int] = {}
    ref_seq = 0
    while model.now_ns - t0 < seconds * 1e9:
        now = model.now_ns
        if (now - t0) % REFERENCE_NS == 0:
            ref_seq += 1
            pos, vel, yaw = mission.samples((now - t0) / 1e9, 0.05, 60)
            planner.put(
                Reference(uav=UAV, seq=ref_seq, stamp_ns=now, dt_s=0.05, pos_m=pos, vel_mps=vel, yaw_rad=yaw)
            )
        bus.pump()
        turn(service, now)
        if (now - t0) % SETPOINT_PERIOD_NS == 0:
            s = model.state
            w, x, y, z = (float(q) for q in s.quat)
            state = FcState(now, _triple(s.pos_m), _triple(s.vel_mps), (w, x, y, z))
            out = core.tick(TickInput(now_ns=now, fc=state, downlink=downlink.drain(), offboard=True))
            for item in out.publish:
                uplink[item.stream, item.flow].put(item.message)
            if now - t0 > 10 * NS_PER_S:
                sources[core.control] = sources.get(core.control, 0) + 1
            sp = out.setpoint
            if isinstance(sp, AccelSetpoint):
                fc.on_setpoint(Setpoint(accel_mps2=sp.accel_mps2, yaw_rad=sp.yaw_rad), now)
            elif sp is not None:
                fc.on_setpoint(Setpoint(pos_m=sp.pos_m, yaw_rad=sp.yaw_rad), now)
        model.step()
        assert model.now_ns - now == STEP_NS
        t = (model.now_ns - t0) / 1e9
        if t > 10.0:
            p, _, _ = mission.sample(t)
            errors.append(float(np.linalg.norm(model.state.pos_m - np.array(p))))
    commands = [i.message for i in observed.drain() if isinstance(i.message, Command)]
    rmse = float(np.sqrt(np.mean(np.square(errors))))
    return Flight(rmse, commands, sources, core, service)


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))
