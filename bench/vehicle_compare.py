"""dynqos's simulated vehicle measured against PX4 itself: the same setpoint stream at 50 Hz, flown by
each after the onboard daemon's own take-off, and the same figures read from what each reports on its
offboard link (LOCAL_POSITION_NED):

- hover: 10 s holding where the take-off ended: the horizontal drift (RMS and largest);
- steps of 1 m in x, y and z (position setpoints, 8 s each): the delay from the setpoint to motion (5% of
  the step), the rise time (10% to 90%), the overshoot and the error at the end;
- an acceleration doublet along x (+1 m/s^2 for 1 s, -1 for 1 s; what the edge's MPC sends is an
  acceleration): the lag of the velocity behind the commanded one and the gain of its peak;
- the demo's circle (2 m, 12 s a lap, position setpoints): the tracking RMSE of the second lap.

Not a speed target: what differs is what the demo's figures inherit from the vehicle (docs/simulator.md
has the table). Run: python -m dynqos.bench.vehicle_compare --px4-dir DIR [--out FILE] [--quick]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import socket
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from dynqos.bench.report import provenance
from dynqos.common.clock import MonotonicClock
from dynqos.common.config import Config, OnboardConfig, Px4Config, VehicleSimConfig, to_toml
from dynqos.common.errors import DynqosError
from dynqos.experiment.processes import Processes, free_port
from dynqos.onboard.fc import hold_at
from dynqos.onboard.fclink import FcLink
from dynqos.onboard.parts import takeoff_commands
from dynqos.onboard.takeoff import Do, TakeoffSequencer
from dynqos.sim.vehicle.px4_sitl import Px4Ports, free_instances

RATE_HZ = 50
ALTITUDE_M = 1.5
Vec3 = tuple[float, float, float]
Sample = tuple[float, Vec3, Vec3]  # seconds since the manoeuvre began, position, velocity


# ---- the figures (pure) -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Step:
    delay_s: float | None  # setpoint to 5% of the step
    rise_s: float | None  # 10% to 90%
    overshoot_pct: float
    final_error_m: float


def step_response(samples: Sequence[tuple[float, float]], start: float, target: float) -> Step:
    """The response of one coordinate (time, value) to a step from `start` to `target` at time 0."""
    size = target - start
    progress = [(t, (v - start) / size) for t, v in samples]

    def first(level: float) -> float | None:
        return next((t for t, p in progress if p >= level), None)

    t10, t90 = first(0.1), first(0.9)
    peak = max((p for _, p in progress), default=0.0)
    return Step(
        delay_s=first(0.05),
        rise_s=None if t10 is None or t90 is None else t90 - t10,
        overshoot_pct=max(0.0, (peak - 1.0) * 100),
        final_error_m=abs(samples[-1][1] - target) if samples else math.nan,
    )


def lag_and_gain(
    times: Sequence[float], wanted: Sequence[float], flown: Sequence[float]
) -> tuple[float, float]:
    """How far `flown` lags `wanted` (the shift, in whole samples up to a second, at which their shapes
    correlate best, whatever their sizes) and the ratio of their peaks."""
    step = statistics.median(b - a for a, b in itertools.pairwise(times)) if len(times) > 1 else 0.02
    best, best_score = 0, -math.inf
    for shift in range(min(round(1.0 / step), len(wanted) - 2)):
        a, b = wanted[: len(wanted) - shift], flown[shift:]
        try:
            score = statistics.correlation(a, b)
        except statistics.StatisticsError:  # one of them constant
            continue
        if score > best_score:
            best, best_score = shift, score
    peak = max(abs(w) for w in wanted) or 1.0
    return best * step, max(abs(f) for f in flown) / peak


def drift(samples: Sequence[Sample], at: Vec3) -> dict[str, float]:
    off = [math.hypot(p[0] - at[0], p[1] - at[1]) for _, p, _ in samples]
    return {"rms_m": math.sqrt(statistics.fmean(d * d for d in off)), "max_m": max(off)}


def circle_rmse(samples: Sequence[Sample], reference: Callable[[float], Vec3], since_s: float) -> float:
    errors = [math.dist(p, reference(t)) for t, p, _ in samples if t >= since_s]
    return math.sqrt(statistics.fmean(e * e for e in errors))


# ---- flying (I/O) -----------------------------------------------------------------------------------


class Flight:
    """Setpoints at RATE_HZ to one vehicle, and what it reports on each tick."""

    def __init__(self, link: FcLink) -> None:
        self.link = link

    def stream(self, seconds: float, setpoint: Callable[[float], tuple[str, Vec3]]) -> list[Sample]:
        samples: list[Sample] = []
        start = time.monotonic()
        tick = start
        while (now := time.monotonic()) - start < seconds:
            kind, value = setpoint(now - start)
            if kind == "accel":
                self.link.send_accel(value, 0.0)
            else:
                self.link.send_position(value, 0.0)
            if (state := self.link.state) is not None:
                samples.append((now - start, state.pos_m, state.vel_mps))
            tick += 1 / RATE_HZ
            time.sleep(max(0.0, tick - time.monotonic()))  # the setpoint rate, as the daemon keeps it
        return samples


def take_off(link: FcLink) -> Vec3:
    """The onboard daemon's own take-off sequence (onboard/takeoff.py) on this link; where it ended."""
    clock = MonotonicClock()
    sequence = TakeoffSequencer(ALTITUDE_M, 30.0, clock.now_ns())
    commands = takeoff_commands(link, ALTITUDE_M)
    while True:
        heard = link.last_heartbeat_ns is not None
        step = sequence.next(clock.now_ns(), link.state, heard, armed=link.armed if heard else None)
        if step.do in commands:
            sequence.answered(commands[step.do](step.confirmation))
        elif step.do is Do.HOLD_SETPOINT and step.hold is not None:
            hold = hold_at(step.hold)
            link.send_position(hold.pos_m, hold.yaw_rad)
        elif step.do is Do.FAILED:
            raise DynqosError(f"take-off failed: {step.reason}")
        elif step.do is Do.DONE and step.hold is not None:
            return step.hold.pos_m
        time.sleep(step.wait_s)


def holding(where: Vec3) -> Callable[[float], tuple[str, Vec3]]:
    return lambda _t: ("pos", where)


def manoeuvres(flight: Flight, at: Vec3, quick: bool) -> dict[str, Any]:
    x, y, z = at
    hold_s, step_s, laps = (4.0, 5.0, 1.5) if quick else (10.0, 8.0, 2.0)
    out: dict[str, Any] = {"hover": drift(flight.stream(hold_s, lambda _t: ("pos", at)), at)}
    steps = {}
    for axis, target in (("x", (x + 1, y, z)), ("y", (x + 1, y + 1, z)), ("z", (x + 1, y + 1, z - 1))):
        before = {"x": at, "y": (x + 1, y, z), "z": (x + 1, y + 1, z)}[axis]
        index = "xyz".index(axis)
        samples = flight.stream(step_s, holding(target))
        response = step_response([(t, p[index]) for t, p, _ in samples], before[index], target[index])
        steps[axis] = asdict(response)
    out["steps"] = steps
    here = (x + 1, y + 1, z - 1)
    flight.stream(2.0, lambda _t: ("pos", here))

    def doublet(t: float) -> tuple[str, Vec3]:
        return "accel", (1.0 if t < 1.0 else -1.0 if t < 2.0 else 0.0, 0.0, 0.0)

    samples = flight.stream(3.0, doublet)
    wanted = [min(t, 2.0 - t) if t < 2.0 else 0.0 for t, _, _ in samples]  # the commanded velocity
    flown = [v[0] - samples[0][2][0] for _, _, v in samples]
    lag, gain = lag_and_gain([t for t, _, _ in samples], wanted, flown)
    out["accel_doublet"] = {"lag_s": lag, "velocity_gain": gain}
    centre = (here[0] - 2.0, here[1], here[2])

    def on_circle(t: float) -> Vec3:
        angle = 2 * math.pi * t / 12.0
        return (centre[0] + 2.0 * math.cos(angle), centre[1] + 2.0 * math.sin(angle), centre[2])

    flight.stream(2.0, lambda _t: ("pos", on_circle(0.0)))
    samples = flight.stream(12.0 * laps, lambda t: ("pos", on_circle(t)))
    out["circle_rmse_m"] = circle_rmse(samples, on_circle, since_s=12.0 * (laps - 1))
    return out


def fly(vehicle: str, px4_dir: str, quick: bool) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="dynqos-compare-") as tmp:
        folder = Path(tmp)
        if vehicle == "px4":
            instance = free_instances(1)[0]
            ports = Px4Ports(instance)
            url, system_id = f"udpin:127.0.0.1:{ports.offboard_remote}", ports.system_id
            config = Config(px4=Px4Config(dir=px4_dir, ulog=False))
            args = ["sim", "px4", "--instance", str(instance), "--workdir", str(folder / "px4")]
        else:
            port = free_port(socket.SOCK_DGRAM)
            url, system_id = f"udpin:127.0.0.1:{port}", 1
            config = Config(
                vehicle=VehicleSimConfig(
                    offboard_bind_port=0,
                    offboard_remote_port=port,
                    gcs_bind_port=0,
                    gcs_remote_port=free_port(socket.SOCK_DGRAM),
                ),
                onboard=OnboardConfig(mavlink_url=url),
            )
            args = ["sim", "vehicle", "--duration", "600"]
        (folder / "dynqos.toml").write_text(to_toml(config))
        (folder / "logs").mkdir()
        procs = Processes(folder / "dynqos.toml", folder / "logs")
        link = FcLink(url, fc_system_id=system_id)
        try:
            procs.start("vehicle", args, timeout_s=60)
            link.start()
            if not link.wait_ready(30):
                raise DynqosError(f"{vehicle}: no heartbeat and position on {url}")
            at = take_off(link)
            return manoeuvres(Flight(link), at, quick)
        finally:
            link.close()
            procs.stop_all()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--px4-dir", required=True, metavar="DIR", help="PX4's folder (docs/px4.md)")
    parser.add_argument("--out", metavar="FILE", help="write the figures as JSON")
    parser.add_argument("--quick", action="store_true", help="shorter manoeuvres")
    args = parser.parse_args(argv)
    result = {name: fly(name, args.px4_dir, args.quick) for name in ("sim", "px4")}
    result["provenance"] = provenance()
    text = json.dumps(result, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
