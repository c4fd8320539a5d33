"""The fleet planner service (edge/planner/fleet_service.py) and what it sends: on an in-process bus
and a made-up clock, each drone's legs as MissionRequests from where it is, each when due, the one being
flown sent again for late planner replicas; against the emulated operator (its control API in this
process, every exchange checked against the official CAMARA documents where the checkout has them),
a plan from the predicted connectivity that books the high-risk inspections and releases every booking,
and the blind plan, said as such, when the operator has no prediction to give."""

from __future__ import annotations

import asyncio
import time
from dataclasses import replace

import pytest

from dynqos.common import keys
from dynqos.common.bus import MemoryBus
from dynqos.common.clock import FakeClock
from dynqos.common.config import (
    Config,
    CoverageHoleConfig,
    DeviceConfig,
    FleetPlanConfig,
    FleetTaskConfig,
    PredictionConfig,
    RadioConfig,
)
from dynqos.common.errors import ConfigError, DynqosError
from dynqos.common.keys import Downlink, Flow, Stream
from dynqos.common.messages import MissionRequest, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import Priority, Received
from dynqos.edge.operator.booking import BookingApi
from dynqos.edge.operator.client import OperatorClient
from dynqos.edge.planner.fleet_plan import Leg, Plan
from dynqos.edge.planner.fleet_schedule import missions_of
from dynqos.edge.planner.fleet_service import FleetPlannerService
from dynqos.edge.runtime import Ports
from tests.edge_cores import take, turn
from tests.test_qod_api import DEVICE, emulated_operator, run

TASKS = (
    FleetTaskConfig(id="a", points_m=((4.0, 0.0),), duration_s=5.0, risk="high"),
    FleetTaskConfig(id="b", points_m=((-4.0, 0.0),), duration_s=5.0),
)
HOLE = CoverageHoleConfig(center_m=(0.0, 0.0), radius_m=1.5, edge_m=0.0, loss_db=60.0, top_m=3.0)


def fleet(**changes: object) -> FleetPlanConfig:
    base = FleetPlanConfig(drones=("uav1",), tasks=TASKS, half_m=(6.0, 6.0), lead_s=1.0, max_bookings=1)
    return replace(base, **changes)  # type: ignore[arg-type]


def state(uav: str, pos: tuple[float, float, float], mode: str = "offboard") -> State:
    return State(uav=uav, seq=1, stamp_ns=0, pos_m=pos, vel_mps=(0.0, 0.0, 0.0), quat=(1.0, 0.0, 0.0, 0.0),
                 mode=mode)  # fmt: skip


def test_the_schedule_sends_each_moving_leg_once_in_ned_in_time_order() -> None:
    climb = ((0.0, 0.0, 1.5), (0.0, 0.0, 1.5), (2.0, 0.0, 1.5), (2.0, 0.0, 5.0))
    plan = Plan(legs={
        "uav2": [Leg("fly", 3.0, 5.0, climb, "x"), Leg("task", 5.0, 9.0, ((2.0, 0.0, 5.0),), "x")],
        "uav1": [Leg("fly", 0.0, 0.0, ((1.0, 1.0, 1.5), (1.0, 1.0, 1.5)), "y"),  # already there: nothing
                 Leg("task", 0.0, 4.0, ((1.0, 1.0, 1.5), (5.0, 1.0, 1.5)), "y")],  # a route: flown
    })  # fmt: skip
    sent = missions_of(plan)
    assert [(m.uav, m.at_s, m.task) for m in sent] == [("uav1", 0.0, "y"), ("uav2", 3.0, "x")]
    assert sent[1].waypoints_m == ((0.0, 0.0, -1.5), (2.0, 0.0, -1.5), (2.0, 0.0, -5.0))


@pytest.mark.parametrize(
    ("changes", "key"),
    [
        ({"tasks": (FleetTaskConfig(id="far", points_m=((30.0, 0.0),)),)}, "tasks.far"),
        ({"tasks": (TASKS[0], TASKS[0])}, "tasks"),
        ({"drones": ("uav1", "uav1")}, "drones"),
        ({"heights_m": ()}, "heights_m"),
    ],
)
def test_a_bad_fleet_plan_is_a_config_error_naming_its_key(changes: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as error:
        fleet(**changes)
    assert error.value.key.endswith(key)


def test_a_route_needs_two_points_and_an_inspection_one() -> None:
    with pytest.raises(ConfigError, match="two or more"):
        FleetTaskConfig(id="r", kind="route", points_m=((0.0, 0.0),))
    with pytest.raises(ConfigError, match="exactly one"):
        FleetTaskConfig(id="i", points_m=((0.0, 0.0), (1.0, 0.0)))


def test_the_blind_plan_is_sent_leg_by_leg_when_due_from_where_each_drone_is() -> None:
    clock = FakeClock(5_000_000_000)
    bus = MemoryBus(clock)
    service = FleetPlannerService(
        Config(fleet_plan=fleet(mode="blind", drones=("uav1", "uav2"))), Ports(bus, clock)
    )
    heard = {uav: BoundedQueue[Received](64) for uav in ("uav1", "uav2")}
    for uav, queue in heard.items():
        bus.subscribe(keys.downlink(uav, Downlink.MISSION), queue, expect=(MissionRequest,))
    up = {u: bus.publisher(keys.uplink(u, Flow.DEFAULT, Stream.STATE), Priority.REAL_TIME) for u in heard}
    up["uav1"].put(state("uav1", (3.0, 1.0, -1.5)))
    up["uav2"].put(state("uav2", (-3.0, -1.0, -1.5), mode="takeoff"))  # not offloading yet: not counted
    take(service, clock.now_ns())
    assert not service.everyone_heard()
    up["uav2"].put(state("uav2", (-3.0, -1.0, -1.5)))
    take(service, clock.now_ns())
    assert service.everyone_heard()

    async def blind() -> None:
        async with OperatorClient(service.config.qos.camara) as operator:
            await service.plan_and_book(BookingApi(operator))  # blind: no operator is asked
            assert operator.calls == 0

    asyncio.run(blind())
    assert service.planned_with == "blind ([fleet_plan] mode)"
    assert service.booked == []
    assert service.plan is not None
    assert service.plan.assigned() == {"a": "uav1", "b": "uav2"}
    assert service.start_ns == clock.now_ns() + 1_000_000_000  # lead_s after the plan

    clock.advance_s(0.5)
    assert service.send_due(clock.now_ns())
    assert service.sent == 0
    clock.advance_s(0.5)
    assert service.send_due(clock.now_ns())
    first = {uav: [i.message for i in q.drain()] for uav, q in heard.items()}
    one = first["uav1"][0]
    assert isinstance(one, MissionRequest)
    assert one.waypoints_m == ((3.0, 1.0, -1.5), (4.0, 0.0, -1.5))  # from where it is, to its task
    assert one.source == "fleet-planner:a"
    assert one.speed_mps == 1.0
    two = first["uav2"][0]
    assert isinstance(two, MissionRequest)
    assert two.waypoints_m[-1] == (-4.0, 0.0, -1.5)
    assert service.sent == 2
    clock.advance_s(1.0)
    service.send_due(clock.now_ns())
    again = heard["uav1"].drain()
    assert [i.message.seq for i in again] == [one.seq]  # the same mission again, for a later replica
    clock.advance_s(service.plan.mission_s + 1.0)
    assert not service.send_due(clock.now_ns())  # the mission is over
    assert service.sent == 2


def _planned(radio: RadioConfig | None) -> tuple[FleetPlannerService, list[object], int]:
    """Plan against the emulated operator, then release; (the service, what the operator holds after
    planning, after releasing)."""
    seen: list[object] = []

    async def main() -> int:
        # geohash level 10 (about 1.2 x 0.6 m here): a hole a few metres wide shows in the prediction
        cell = {} if radio is None else {"radio": radio, "prediction": PredictionConfig(precisions=(9, 10))}
        async with emulated_operator(**cell) as op:
            config = Config(
                fleet_plan=fleet(precision=10),
                qos=replace(Config().qos, camara=op.camara(devices={"uav1": DeviceConfig(**DEVICE)})),
            )
            service = FleetPlannerService(config, Ports(MemoryBus(FakeClock(time.monotonic_ns()))))
            service.positions = {"uav1": (-5.0, -5.0, -1.5)}
            async with OperatorClient(
                config.qos.camara
            ) as operator:  # the planner's one client, from plan to release
                booking = BookingApi(operator)
                await service.plan_and_book(booking)
                seen.append(service)
                seen.append(await booking.retrieve(DEVICE))
                assert service.bookings_held() == sum(1 for b in service.booked if b["booking_id"])
                await service.release(booking)
                assert service.bookings_held() == 0
                return len(await booking.retrieve(DEVICE))

    left = 0

    async def wrapped() -> None:
        nonlocal left
        left = await main()

    run(wrapped())
    service = seen[0]
    assert isinstance(service, FleetPlannerService)
    return service, seen[1:], left


def test_a_planned_mission_books_its_high_risk_inspection_and_releases_every_booking() -> None:
    service, (held,), left = _planned(RadioConfig(enabled=True, position_port=0, holes=(HOLE,)))
    assert service.planned_with == "prediction"
    assert service.plan is not None
    assert [(b["drone"], b["task"], b["status"]) for b in service.booked] == [("uav1", "a", "SCHEDULED")]
    assert isinstance(held, list)
    assert [b.booking_id for b in held] == [service.booked[0]["booking_id"]]
    assert service.released == [service.booked[0]["booking_id"]]
    assert service.release_failed == []
    assert left == 0  # nothing stays booked
    # the route from (-5, -5) past the hole at the origin does not cross it at 1.5 m
    for legs in service.plan.legs.values():
        for leg in legs:
            for x, y, h in leg.path_m:
                assert h > 3.0 or (x * x + y * y) ** 0.5 > 1.5 - 1e-6


def test_without_a_prediction_the_blind_plan_is_flown_and_says_why() -> None:
    service, _, left = _planned(None)  # an operator without a radio map serves no prediction
    assert service.planned_with.startswith("blind: the prediction failed (")
    assert service.plan is not None
    assert service.plan.assigned() == {"a": "uav1", "b": "uav1"}
    assert service.booked == []
    assert left == 0


def test_its_ticks_wait_for_every_drone_then_name_the_silent_ones_and_end_the_mission_when_flown() -> None:
    """The phases as the runtime drives them: waiting until every drone is heard (past wait_s, an error
    naming the silent ones), then, once planned, flying until the last leg is past (`over` set)."""
    clock = FakeClock(5_000_000_000)
    bus = MemoryBus(clock)
    config = Config(fleet_plan=fleet(mode="blind", drones=("uav1", "uav2"), wait_s=10.0))
    silent = FleetPlannerService(config, Ports(bus, clock))
    up = bus.publisher(keys.uplink("uav1", Flow.DEFAULT, Stream.STATE), Priority.REAL_TIME)
    up.put(state("uav1", (3.0, 1.0, -1.5)))
    turn(silent, clock.now_ns())
    assert not silent.heard.is_set()
    clock.advance_s(10.5)
    with pytest.raises(DynqosError, match="never heard uav2 in offboard mode within 10 s"):
        turn(silent, clock.now_ns())

    service = FleetPlannerService(config, Ports(bus, clock))
    for uav in ("uav1", "uav2"):
        bus.publisher(keys.uplink(uav, Flow.DEFAULT, Stream.STATE), Priority.REAL_TIME).put(
            state(uav, (3.0, 1.0, -1.5))
        )
    turn(service, clock.now_ns())
    assert service.heard.is_set()

    async def planned() -> None:
        async with OperatorClient(config.qos.camara) as operator:
            await service.plan_and_book(BookingApi(operator))

    asyncio.run(planned())
    service.phase = "flying"  # as its mission task sets it once planned
    assert service.plan is not None
    clock.advance_s(1.0)
    assert turn(service, clock.now_ns()) <= 0.1
    assert service.sent == 2
    assert not service.over.is_set()
    clock.advance_s(service.plan.mission_s + 1.0)
    turn(service, clock.now_ns())
    assert service.phase == "done"
    assert service.over.is_set()
