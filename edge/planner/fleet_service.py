"""`dynqos edge fleet-planner`: plans the fleet's mission by the network it will meet and flies it.

Thin around the pure planner (edge/planner/fleet_plan.py, docs/planning.md): it waits until every drone
of `[fleet_plan] drones` is heard in offboard mode (where each is, is where it starts), asks the
operator for the predicted connectivity over the arena and the mission's time (CAMARA Predictive
Connectivity Data), plans, books priority for the plan's high-risk inspections (CAMARA QoS Booking), and
sends each drone its legs as MissionRequests when they are due; the planner replicas fly them. Without a
prediction (the operator refused or failed) it flies the blind plan and says why; a booking refused
leaves that inspection to QoD on demand. Every booking is released when the mission ends or the
service stops. `plan_file` gets the plan and what became of it, for the scenario's report.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from dynqos.common import keys
from dynqos.common.bus import Priority, Publisher, Received
from dynqos.common.config import Config
from dynqos.common.errors import DynqosError
from dynqos.common.geo import Geo
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import OFFBOARD, MissionRequest, State
from dynqos.edge import metrics
from dynqos.edge.operator.booking import BookingApi, circle
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.connectivity import ConnectivityApi, PredictedLevels
from dynqos.edge.planner.fleet_plan import Plan, plan
from dynqos.edge.planner.fleet_schedule import (
    Ned,
    TimedMission,
    drones_at,
    missions_of,
    settings_of,
    tasks_of,
)
from dynqos.edge.resend import LatestMissions
from dynqos.edge.runtime import EdgeCore, Ports, Runtime, serve

log = logging.getLogger(__name__)

DONE_AFTER_S = 1.0  # past the plan's last leg, the mission is over and its bookings are released


class FleetPlannerService(EdgeCore):
    """Its phases: waiting (for every drone), planning (the operator's prediction and bookings, the one
    task of its own, `_mission`), flying (each leg sent when due, at `tick`), done or stopped."""

    name = "fleet-planner"

    def __init__(self, config: Config, ports: Ports) -> None:
        bus = ports.bus
        self.config = config
        self.cfg = config.fleet_plan
        self.bus = bus
        self.clock = ports.clock
        self.health_interval_s = self.cfg.health_interval_s
        self.geo = Geo(self.cfg.origin_lat_deg, self.cfg.origin_lon_deg)
        self.inbox = ports.inbox
        bus.subscribe(keys.uplink_all_drones(Stream.STATE), self.inbox, expect=(State,))
        self.wait_until_ns = self.clock.now_ns() + round(self.cfg.wait_s * 1e9)
        self.publishers: dict[str, Publisher] = {
            uav: bus.publisher(keys.downlink(uav, Downlink.MISSION), Priority.INTERACTIVE_HIGH)
            for uav in self.cfg.drones
        }
        self.positions: dict[str, Ned] = {}
        self.plan: Plan | None = None
        self.planned_with = ""  # "prediction", or why the blind plan is flown
        self.start_unix = 0.0
        self.start_ns = 0
        self.missions: list[TimedMission] = []
        self.sent = 0  # missions sent (each once; re-sends not counted)
        self.booked: list[dict[str, Any]] = []
        self.booking: BookingApi | None = None  # the one booking client, once planning starts
        self.released: list[str] = []
        self.release_failed: list[str] = []
        self.phase = "waiting"
        self._due: list[TimedMission] = []  # the missions not sent yet, in time order
        self._latest = LatestMissions(0)  # each drone's leg being flown, sent again for late replicas
        self._seq = time.time_ns() // 1_000_000  # newer than any earlier life's (planner.service's rule)
        self.heard = asyncio.Event()  # every drone heard: planning may start
        self.over = asyncio.Event()  # the mission is over: its bookings may go

    # ---- phases ----------------------------------------------------------------------------------------

    def handle(self, events: list[Received], now_ns: int) -> None:
        """Where each drone of the fleet is, from its newest state in offboard mode."""
        for item in events:
            message = item.message
            if isinstance(message, State) and message.uav in self.publishers and message.mode == OFFBOARD:
                self.positions[message.uav] = message.pos_m

    def everyone_heard(self) -> bool:
        return self.positions.keys() >= self.publishers.keys()

    def tick(self, now_ns: int) -> float:
        """Waiting: every drone heard, or DynqosError naming the silent ones past `wait_s`. Flying: the
        legs due."""
        if self.phase == "waiting":
            if self.everyone_heard():
                self.heard.set()
            elif now_ns > self.wait_until_ns:
                missing = sorted(self.publishers.keys() - self.positions.keys())
                raise DynqosError(
                    f"fleet planner: never heard {', '.join(missing)} in offboard mode "
                    f"within {self.cfg.wait_s:g} s ([fleet_plan] wait_s)"
                )
            return 0.1
        if self.phase != "flying":
            return 0.5
        if not self.send_due(now_ns):
            self.phase = "done"
            self.over.set()
            log.info("fleet planner: mission done; %s", self.health())
            return 0.5
        ahead = self._due[0].at_s - (now_ns - self.start_ns) / 1e9 if self._due else 0.1
        return min(0.1, max(0.005, ahead))

    async def plan_and_book(self, booking: BookingApi) -> None:
        """The plan (from the prediction unless blind or it failed), then its bookings, over the planner's
        one operator client (`booking.operator`)."""
        self.booking = booking
        self.start_unix = time.time() + self.cfg.lead_s
        self.start_ns = self.clock.now_ns() + round(self.cfg.lead_s * 1e9)
        tasks, settings = tasks_of(self.cfg), settings_of(self.cfg)
        drones = drones_at(self.positions, self.cfg.speed_mps)
        blind = plan(tasks, drones, None, settings, blind=True)
        if self.cfg.mode == "blind":
            self.plan, self.planned_with = blind, "blind ([fleet_plan] mode)"
        else:
            # as far ahead as a plan some 50% longer than the blind one may need (past it: ND)
            levels = await self._predict(booking.operator, horizon_s=1.5 * blind.mission_s + 30.0)
            if levels is None:
                self.plan = blind
            else:
                self.plan, self.planned_with = plan(tasks, drones, levels, settings), "prediction"
            await self._book(booking)
        self.missions = missions_of(self.plan)
        self._due = list(self.missions)
        log.info(
            "fleet planner: %s plan (%s): %d tasks on %d drones, mission %.1f s, %d legs, %d booked, %d "
            "left to QoD on demand",
            self.cfg.mode,
            self.planned_with,
            len(tasks),
            len(drones),
            self.plan.mission_s,
            len(self.missions),
            len(self.booked),
            len(self.plan.unbooked),
        )

    async def _predict(self, operator: OperatorClient, horizon_s: float) -> PredictedLevels | None:
        hx, hy = self.cfg.half_m
        corners = [self.geo.to_latlon(x, y) for x, y in ((-hx, -hy), (-hx, hy), (hx, hy), (hx, -hy))]
        end = self.start_unix + horizon_s
        try:
            prediction = await ConnectivityApi(operator).retrieve(
                corners,
                self.start_unix,
                end,
                service_level=self.cfg.service_level,
                precision=self.cfg.precision,
                timeout_s=self.cfg.prediction_timeout_s,
            )
        except OperatorError as exc:
            self.planned_with = f"blind: the prediction failed ({exc})"
            log.warning("fleet planner: no prediction, flying the blind plan: %s", exc)
            return None
        return PredictedLevels(prediction, self.geo, self.start_unix, self.cfg.precision)

    async def _book(self, client: BookingApi) -> None:
        """Book each planned window; a refusal leaves that inspection to QoD on demand."""
        assert self.plan is not None
        camara = self.config.qos.camara
        server = {"ipv4Address": camara.application_server or self.config.zenoh.edge_host}
        for want in self.plan.bookings:
            device = camara.devices.get(want.drone)
            entry: dict[str, Any] = {**asdict(want), "booking_id": "", "status": ""}
            if device is None:
                entry["status"] = "no device"
                log.warning(
                    "fleet planner: %s has no [qos.camara.devices] entry: %s left to QoD on demand",
                    want.drone,
                    want.task,
                )
            else:
                try:
                    area = circle(self.geo.to_latlon(*want.center_m), want.radius_m)
                    info = await client.book(
                        device.as_api(),
                        self.start_unix + want.start_s,
                        max(1, math.ceil(want.duration_s)),
                        area,
                        qos_profile=camara.qos_profile,
                        server=server,
                        server_ports=[self.config.zenoh.priority_port],
                    )
                    entry.update(booking_id=info.booking_id, status=info.status)
                except OperatorError as exc:
                    entry["status"] = f"refused: {exc}"
                    log.warning(
                        "fleet planner: booking for %s's %s refused, left to QoD on demand: %s",
                        want.drone,
                        want.task,
                        exc,
                    )
            if not entry["booking_id"]:
                self.plan.unbooked.append(want.task)
            self.booked.append(entry)

    def send_due(self, now_ns: int) -> bool:
        """Send the missions due by now (each drone's current one again every second); False once the
        mission is over."""
        assert self.plan is not None
        t_s = (now_ns - self.start_ns) / 1e9
        while self._due and self._due[0].at_s <= t_s:
            leg = self._due.pop(0)
            self._seq += 1
            request = MissionRequest(
                uav=leg.uav,
                seq=self._seq,
                stamp_ns=now_ns,
                waypoints_m=leg.waypoints_m,
                speed_mps=self.cfg.speed_mps,
                source=f"fleet-planner:{leg.task}",
            )
            self._latest.send(request, self.publishers[leg.uav], now_ns)
            self.sent += 1
            log.info(
                "fleet planner: %s leaves for %s at t=%.1f s (%d waypoints)",
                leg.uav,
                leg.task,
                t_s,
                len(leg.waypoints_m),
            )
        self._latest.resend_due(now_ns)
        return t_s < self.plan.mission_s + DONE_AFTER_S

    async def release(self, booking: BookingApi) -> None:
        """Delete every booking `booking` made that has not ended."""
        if not booking.made:
            return
        ids = list(booking.made)
        self.release_failed = await booking.release_all()
        self.released = [i for i in ids if i not in self.release_failed]
        log.info(
            "fleet planner: released %d bookings%s",
            len(self.released),
            f"; could not release {self.release_failed}" if self.release_failed else "",
        )

    # ---- what it says ----------------------------------------------------------------------------------

    def bookings_held(self) -> int:
        """Bookings made and not released."""
        return len(self.booking.made) if self.booking is not None else 0

    def write_plan(self) -> None:
        if not self.cfg.plan_file or self.plan is None:
            return
        record = {
            "mode": self.cfg.mode,
            "planned_with": self.planned_with,
            "phase": self.phase,
            "start_unix": self.start_unix,
            "start_monotonic_ns": self.start_ns,
            "mission_s": self.plan.mission_s,
            "predicted_nc_s": self.plan.predicted_nc_s,
            "tasks": [asdict(t) for t in self.cfg.tasks],
            "start_m": {uav: list(p) for uav, p in self.positions.items()},
            "legs": {uav: [asdict(leg) for leg in legs] for uav, legs in self.plan.legs.items()},
            "bookings": self.booked,
            "unbooked": self.plan.unbooked,
            "missions_sent": self.sent,
            "released": self.released,
            "release_failed": self.release_failed,
        }
        path = Path(self.cfg.plan_file)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
        tmp.replace(path)

    def health(self) -> str:
        heard = f"{len(self.positions)}/{len(self.cfg.drones)}"
        mission = f"{self.plan.mission_s:.0f}s" if self.plan is not None else "-"
        booked = sum(1 for b in self.booked if b["booking_id"])
        return (
            f"{self.phase} drones={heard} mission={mission} sent={self.sent}/{len(self.missions)} "
            f"booked={booked} released={len(self.released)}"
        )

    async def start(self, runtime: Runtime) -> None:
        runtime.task(self._mission(runtime))

    async def _mission(self, runtime: Runtime) -> None:
        """One operator client for the planner's life: the prediction, the bookings, their release once
        the mission is over or the service stops (it stays up, healthy, until stopped)."""
        async with OperatorClient(self.config.qos.camara) as operator:
            booking = BookingApi(operator)
            try:
                if not await runtime.until(self.heard):
                    return
                self.phase = "planning"
                await self.plan_and_book(booking)
                self.phase = "flying"
                self.write_plan()
                runtime.wake()
                await runtime.until(self.over)
            finally:
                if self.phase != "done":
                    self.phase = "stopped"
                await self.release(booking)
                self.write_plan()


def run(config: Config, *, health_file: Path | None = None) -> int:
    """`dynqos edge fleet-planner` until SIGTERM."""
    if not config.fleet_plan.drones or not config.fleet_plan.tasks:
        raise DynqosError("fleet planner: [fleet_plan] needs drones and tasks (docs/planning.md)")
    return serve("fleet-planner", config, FleetPlannerService, metrics.fleet_planner, health_file=health_file)
