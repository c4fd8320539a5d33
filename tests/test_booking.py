"""CAMARA QoS Booking 0.1.0: the emulated operator's bookings (sim/network/booking.py) on a made-up clock,
and the edge's client (edge/operator/booking.py) against the emulated operator in this process, every
exchange checked against the official CAMARA document where the checkout has it."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.camara import rfc3339
from dynqos.common.config import CellConfig, PredictionConfig, RadioConfig
from dynqos.common.geo import Geo
from dynqos.edge.operator.booking import BookingApi, BookingInfo, booking_root, circle
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.sim.network.booking import KEEP_UNAVAILABLE_S, Bookings
from dynqos.sim.network.operator import Operator
from dynqos.sim.network.operator_apis import OperatorApis
from tests.test_qod_api import DEVICE, SECRET, emulated_operator, run

GEO = Geo(PredictionConfig().origin_lat_deg, PredictionConfig().origin_lon_deg)
T0 = 1_800_000_000.0


class Clock:
    def __init__(self) -> None:
        self.now = T0

    def __call__(self) -> float:
        return self.now


def bookings(where: tuple[float, float] | None = None, max_concurrent: int = -1) -> tuple[Bookings, Clock]:
    clock = Clock()
    operator = Operator(CellConfig(qod=True), {"uav1": DEVICE, "uav2": {"phoneNumber": "+46700000002"}},
                        {"uav1": "127.0.0.1", "uav2": "127.0.0.1"}, time.monotonic, clock)  # fmt: skip
    books = Bookings(operator, clock, GEO, lambda uav: where, lambda x, y: abs(x) < 20 and abs(y) < 20,
                     max_concurrent)  # fmt: skip
    return books, clock


def body(start: float, duration: int = 30, device: dict[str, Any] = DEVICE, **changes: Any) -> dict[str, Any]:
    return {
        "device": device, "qosProfile": "QOS_E", "startTime": rfc3339(start), "duration": duration,
        "serviceArea": circle(GEO.to_latlon(0.0, 0.0), 5.0), "applicationServerPorts": {"ports": [7448]},
        **changes,
    }  # fmt: skip


def test_a_booking_is_scheduled_then_available_in_its_area_then_expires() -> None:
    books, clock = bookings(where=(1.0, 1.0))
    operator = OperatorApis(books.operator, books)  # a QoD session or a booking grants, as the cell asks
    answer, _ = books.create(body(T0 + 10))
    assert answer.status == 201
    info = BookingInfo.parse(answer.body)
    assert info.status == "SCHEDULED"
    assert not operator.granted("uav1", 7448)
    clock.now = T0 + 11
    operator.advance()
    assert books.get(info.booking_id).body["status"] == "AVAILABLE"
    assert operator.granted("uav1", 7448)
    assert not operator.granted("uav1", 7447)  # another flow: not booked
    assert not operator.granted("uav2", 7448)
    books.where = lambda uav: (9.0, 0.0)  # out of the 5 m circle: no priority there
    assert not operator.granted("uav1", 7448)
    clock.now = T0 + 41
    operator.advance()
    ended = books.get(info.booking_id).body
    assert (ended["status"], ended["statusInfo"]) == ("UNAVAILABLE", "DURATION_EXPIRED")
    clock.now = T0 + 41 + KEEP_UNAVAILABLE_S
    operator.advance()
    assert books.get(info.booking_id).status == 404  # forgotten, as the API allows


def test_overlaps_conflict_admission_refuses_and_deletion_releases() -> None:
    books, _ = bookings(max_concurrent=1)
    first, _ = books.create(body(T0 + 10))
    again, _ = books.create(body(T0 + 20))
    assert (again.status, again.body["code"]) == (409, "CONFLICT")  # the same device's flow overlaps
    later, _ = books.create(body(T0 + 100))
    assert later.status == 201  # after the first: no overlap
    other, _ = books.create(body(T0 + 15, device={"phoneNumber": "+46700000002"}))
    assert (other.status, other.body["status"]) == (201, "UNAVAILABLE")  # beyond the admission limit
    assert books.refused == 1
    gone, _ = books.delete(first.body["bookingId"])
    assert gone.status == 204
    assert books.get(first.body["bookingId"]).status == 404
    assert books.delete(first.body["bookingId"])[0].status == 404


@pytest.mark.parametrize(
    ("changes", "status", "code"),
    [
        (
            {"serviceArea": {"areaType": "AREANAME", "areaName": "Stockholm"}},
            422,
            "QOS_BOOKING.NOT_MANAGED_AREA_TYPE",
        ),
        ({"serviceArea": circle(GEO.to_latlon(500.0, 500.0), 5.0)}, 422, "QOS_BOOKING.AREA_NOT_COVERED"),
        ({"qosProfile": "QOS_XL"}, 422, "SERVICE_NOT_APPLICABLE"),
        ({"device": {"phoneNumber": "+46709999999"}}, 404, "IDENTIFIER_NOT_FOUND"),
        ({"startTime": rfc3339(T0 - 60)}, 400, "OUT_OF_RANGE"),
        ({"duration": 0}, 400, "INVALID_ARGUMENT"),
        ({"colour": "red"}, 400, "INVALID_ARGUMENT"),
    ],
)
def test_refusals_carry_the_apis_codes(changes: dict[str, Any], status: int, code: str) -> None:
    books, _ = bookings()
    answer, _ = books.create(body(T0 + 10) | changes)
    assert (answer.status, answer.body["code"]) == (status, code)


def test_the_root_is_beside_the_qod_api() -> None:
    from dynqos.common.config import CamaraConfig

    assert booking_root(CamaraConfig(api_root="https://op.example/x/quality-on-demand/v1")) == (
        "https://op.example/x/qos-booking/v0.1"
    )


# ---- the client against the emulated operator -----------------------------------------------------------


def test_the_client_books_reads_lists_and_releases_everything_it_made() -> None:
    async def main() -> None:
        async with emulated_operator() as op, OperatorClient(op.camara()) as operator:
            client = BookingApi(operator)
            now = time.time()
            area = circle(GEO.to_latlon(0.0, 0.0), 10.0)
            soon = await client.book(DEVICE, now + 2, 20, area, qos_profile="QOS_E", server_ports=[7448])
            later = await client.book(DEVICE, now + 60, 20, area, qos_profile="QOS_E", server_ports=[7448])
            assert soon.status == later.status == "SCHEDULED"
            with pytest.raises(OperatorError) as conflict:
                await client.book(DEVICE, now + 5, 20, area, qos_profile="QOS_E", server_ports=[7448])
            assert (conflict.value.status, conflict.value.code) == (409, "CONFLICT")

            async def available() -> bool:
                return (await client.get(soon.booking_id)).status == "AVAILABLE"

            deadline = time.monotonic() + 5
            while not await available():
                assert time.monotonic() < deadline
                await asyncio.sleep(0.05)  # the operator's own clock starts it
            # no radio map: the booking grants anywhere, from the cell's next grant update (its bearers'
            # counters can lag the booking's status by that tick on a loaded machine)
            while not await op.granted():
                assert time.monotonic() < deadline
                await asyncio.sleep(0.05)
            listed = {b.booking_id for b in await client.retrieve(DEVICE)}
            assert listed == {soon.booking_id, later.booking_id}
            assert await client.release_all() == []
            assert await client.retrieve(DEVICE) == []
            assert not await op.granted()
            assert client.made == {}

    run(main())


def test_bookings_need_a_token_with_their_scope(tmp_path: Path) -> None:
    async def main() -> None:
        secret = tmp_path / "secret"
        secret.write_text(SECRET + "\n")
        async with emulated_operator(qod_auth=True) as op:
            token_url = f"http://127.0.0.1:{op.port}/oauth2/token"
            area = circle(GEO.to_latlon(0.0, 0.0), 10.0)
            async with OperatorClient(op.camara()) as anonymous:
                with pytest.raises(OperatorError) as unauthenticated:
                    await BookingApi(anonymous).book(DEVICE, time.time() + 5, 10, area, qos_profile="QOS_E")
                assert unauthenticated.value.status == 401
            narrow = op.camara(token_url=token_url, client_id="dynqos-test", client_secret_file=str(secret),
                               scope="quality-on-demand:sessions:create")  # fmt: skip
            async with OperatorClient(narrow) as operator:
                with pytest.raises(OperatorError) as forbidden:
                    await BookingApi(operator).book(DEVICE, time.time() + 5, 10, area, qos_profile="QOS_E")
                assert (forbidden.value.status, forbidden.value.code) == (403, "PERMISSION_DENIED")
            agent = op.camara(token_url=token_url, client_id="dynqos-test", client_secret_file=str(secret))
            async with OperatorClient(agent) as operator:
                client = BookingApi(operator)
                made = await client.book(DEVICE, time.time() + 5, 10, area, qos_profile="QOS_E")
                assert made.status == "SCHEDULED"
                assert await client.release_all() == []

    run(main())


def test_without_the_qod_operator_there_are_no_bookings() -> None:
    async def main() -> None:
        radio = RadioConfig(enabled=True, position_port=0)
        async with emulated_operator(qod=False, radio=radio) as op, OperatorClient(op.camara()) as operator:
            with pytest.raises(OperatorError) as missing:
                await BookingApi(operator).get("6f0d8f5e-1c7c-4d5b-9b1e-2a9d7c3e4f50")
            assert missing.value.status == 404

    run(main())
