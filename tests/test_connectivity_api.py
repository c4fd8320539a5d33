"""The Predictive Connectivity Data client (edge/operator/connectivity.py) against the emulated operator (its
control API in this process, every exchange checked against the official CAMARA document where the
checkout has it), and against a scripted server for what only a misbehaving operator does: throttle,
fail, hang, answer nonsense."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pygeohash
import pytest
from aiohttp import web

from dynqos.common.config import CamaraConfig, CoverageHoleConfig, PredictionConfig, RadioConfig
from dynqos.common.geo import Geo
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.connectivity import (
    ConnectivityApi,
    PredictedLevels,
    connectivity_root,
    parse_prediction,
)
from dynqos.edge.planner.fleet_plan import PlanDrone, PlanSettings, Router, Task, plan
from tests.test_qod_api import SECRET, emulated_operator, run

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

HOLE = CoverageHoleConfig(center_m=(-3.0, 0.0), radius_m=1.5, edge_m=0.0, loss_db=60.0, top_m=3.0)
RADIO = RadioConfig(enabled=True, position_port=0, holes=(HOLE,))
GEO = Geo(PredictionConfig().origin_lat_deg, PredictionConfig().origin_lon_deg)
ARENA = [GEO.to_latlon(x, y) for x, y in ((-3.5, -3.5), (3.5, -3.5), (3.5, 3.5), (-3.5, 3.5))]


def test_the_root_is_beside_the_qod_api_unless_set() -> None:
    assert connectivity_root(CamaraConfig(api_root="https://op.example/camara/quality-on-demand/v1")) == (
        "https://op.example/camara/predictive-connectivity-data/v0.1"
    )
    assert (
        connectivity_root(
            CamaraConfig(
                api_root="https://op.example/quality-on-demand/v1", connectivity_root="https://p.example/v0/"
            )
        )
        == "https://p.example/v0"
    )


def test_a_prediction_of_the_arena_marks_the_hole_and_clears_above_it() -> None:
    async def main() -> None:
        async with emulated_operator(radio=RADIO) as op, OperatorClient(op.camara()) as operator:
            client = ConnectivityApi(operator)
            now = time.time()
            low = await client.retrieve(ARENA, now + 1, now + 21, service_level="STREAM_4K", precision=9,
                                        signal_strength=True)  # fmt: skip
            assert low.status == "SUPPORTED_AREA"
            assert low.layer_thickness_m == 2.0
            assert len(low.slots) in (2, 3)
            hole = pygeohash.encode(*GEO.to_latlon(-3.0, 0.0), precision=9)
            far = pygeohash.encode(*GEO.to_latlon(3.0, 3.0), precision=9)
            assert low.level(hole, now + 5, layer=0) == "NC"
            assert low.level(hole, now + 5, layer=2) in ("GC", "MC")  # 4-6 m: above the hole's top
            assert low.level(far, now + 5, layer=0) in ("GC", "MC")
            assert low.level(far, now + 3600) == "ND"  # a time it was not asked about
            cell = low.slots[0].cells[hole]
            assert len(cell.rsrp_dbm) == len(cell.levels) == 4
            high = await client.retrieve(ARENA, now + 1, now + 11, precision=9, height_m=5)
            assert high.requested_height_m == 5
            assert high.level(hole, now + 5) in ("GC", "MC")
            # read by the fleet planner, in its own metres and seconds: it routes round the hole
            levels = PredictedLevels(low, GEO, start_unix=now + 1, precision=9)
            assert levels.level(-3.0, 0.0, 1.0, 4.0) == "NC"
            assert levels.level(-3.0, 0.0, 5.0, 4.0) in ("GC", "MC")
            arena = PlanSettings(half_m=(3.5, 3.5), grid_m=0.5, heights_m=(1.0,))
            task = Task("look", "inspect", ((-3.0, 3.0),), duration_s=1.0)
            routed = plan([task], [PlanDrone("uav1", (-3.0, -3.0))], levels, arena)
            assert routed.legs["uav1"][0].nc_s == 0.0
            assert (
                Router(levels, arena).nc_length([(-3.0, -3.0), (-3.0, 3.0)], 1.0, 4.0) > 1.0
            )  # straight: in it

    run(main())


@pytest.mark.parametrize(
    ("changes", "status", "code"),
    [
        ({"precision": 7}, 422, "PREDICTIVE_CONNECTIVITY_DATA.UNSUPPORTED_PRECISION"),
        ({"start": -120.0, "end": -60.0}, 400, "PREDICTIVE_CONNECTIVITY_DATA.MIN_STARTTIME_EXCEEDED"),
        ({"start": 30.0, "end": 20.0}, 400, "PREDICTIVE_CONNECTIVITY_DATA.INVALID_END_TIME"),
        ({"height_m": 300}, 400, "INVALID_ARGUMENT"),  # outside the schema: the operator's 400
    ],
)
def test_refusals_reach_the_caller_as_the_apis_codes(changes: dict[str, Any], status: int, code: str) -> None:
    async def main() -> None:
        async with (
            emulated_operator(radio=RADIO, requests_valid=False) as op,
            OperatorClient(op.camara()) as operator,
        ):
            now = time.time()
            start, end = now + changes.pop("start", 1.0), now + changes.pop("end", 11.0)
            with pytest.raises(OperatorError) as refused:
                await ConnectivityApi(operator).retrieve(ARENA, start, end, **{"precision": 9, **changes})
            assert (refused.value.status, refused.value.code) == (status, code)
            assert not refused.value.transient  # asking again cannot help

    run(main())


def test_no_radio_map_is_a_404() -> None:
    async def main() -> None:
        async with emulated_operator() as op, OperatorClient(op.camara()) as operator:
            with pytest.raises(OperatorError) as missing:
                await ConnectivityApi(operator).retrieve(
                    ARENA, time.time() + 1, time.time() + 11, precision=9
                )
            assert (missing.value.status, missing.value.code) == (404, "NOT_FOUND")

    run(main())


def test_a_token_is_needed_and_must_carry_the_scope(tmp_path: Path) -> None:
    async def main() -> None:
        secret = tmp_path / "secret"
        secret.write_text(SECRET + "\n")
        async with emulated_operator(radio=RADIO, qod_auth=True) as op:
            token_url = f"http://127.0.0.1:{op.port}/oauth2/token"
            now = time.time()
            async with OperatorClient(op.camara()) as anonymous:
                with pytest.raises(OperatorError) as unauthenticated:
                    await ConnectivityApi(anonymous).retrieve(ARENA, now + 1, now + 11, precision=9)
                assert unauthenticated.value.status == 401
            narrow = op.camara(token_url=token_url, client_id="dynqos-test", client_secret_file=str(secret),
                               scope="quality-on-demand:sessions:create")  # fmt: skip
            async with OperatorClient(narrow) as operator:
                with pytest.raises(OperatorError) as forbidden:
                    await ConnectivityApi(operator).retrieve(ARENA, now + 1, now + 11, precision=9)
                assert (forbidden.value.status, forbidden.value.code) == (403, "PERMISSION_DENIED")
            agent = op.camara(token_url=token_url, client_id="dynqos-test", client_secret_file=str(secret))
            async with OperatorClient(agent) as operator:  # the agent's own scopes include the prediction's
                answer = await ConnectivityApi(operator).retrieve(ARENA, now + 1, now + 11, precision=9)
                assert answer.status == "SUPPORTED_AREA"

    run(main())


# ---- what only a scripted operator does ------------------------------------------------------------------

GOOD = {"layerThickness": 30, "status": "AREA_NOT_SUPPORTED", "timedConnectivityData": []}
BUSY = {"status": 429, "code": "TOO_MANY_REQUESTS", "message": "slow down"}
DOWN = {"status": 503, "code": "UNAVAILABLE", "message": "maintenance"}


@contextlib.asynccontextmanager
async def scripted(
    answers: list[tuple[int, dict[str, str], Any, float]],
) -> AsyncIterator[tuple[str, list[int]]]:
    """A server answering POST .../retrieve with the scripted (status, headers, body, delay_s) in turn."""
    seen: list[int] = []

    async def handler(request: web.Request) -> web.Response:
        await request.json()
        status, headers, body, delay = answers[min(len(seen), len(answers) - 1)]
        seen.append(status)
        await asyncio.sleep(delay)
        return web.json_response(body, status=status, headers=headers)

    app = web.Application()
    app.router.add_post("/predictive-connectivity-data/v0.1/retrieve", handler)
    runner = web.AppRunner(app)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", 0).start()
    try:
        yield f"http://127.0.0.1:{runner.addresses[0][1]}/quality-on-demand/v1", seen
    finally:
        await runner.cleanup()


def test_throttling_and_failures_are_retried_then_answered() -> None:
    async def main() -> None:
        script = [(429, {"Retry-After": "0.05"}, BUSY, 0.0), (503, {}, DOWN, 0.0), (200, {}, GOOD, 0.0)]
        async with (
            scripted(script) as (root, seen),
            OperatorClient(CamaraConfig(api_root=root, timeout_s=3)) as operator,
        ):
            answer = await ConnectivityApi(operator).retrieve(ARENA, time.time() + 1, time.time() + 11)
            assert answer.status == "AREA_NOT_SUPPORTED"
            assert seen == [429, 503, 200]

    run(main())


def test_a_failing_operator_is_a_transient_error_and_a_hanging_one_is_cut_off() -> None:
    async def main() -> None:
        async with (
            scripted([(500, {}, DOWN, 0.0)]) as (root, seen),
            OperatorClient(CamaraConfig(api_root=root, timeout_s=2)) as operator,
        ):
            with pytest.raises(OperatorError) as failed:
                await ConnectivityApi(operator).retrieve(ARENA, time.time() + 1, time.time() + 11)
            assert failed.value.status == 500
            assert failed.value.transient
            assert len(seen) == 4  # the first try and three retries
        async with (
            scripted([(200, {}, GOOD, 5.0)]) as (root, _),
            OperatorClient(CamaraConfig(api_root=root, timeout_s=0.3)) as operator,
        ):
            started = time.monotonic()
            with pytest.raises(OperatorError) as hung:
                await ConnectivityApi(operator).retrieve(ARENA, time.time() + 1, time.time() + 11)
            assert hung.value.code == "TIMEOUT"
            assert time.monotonic() - started < 2.0
        # one client for every call (the fleet planner's): the prediction's own time-out, longer or shorter
        async with (
            scripted([(200, {}, GOOD, 1.0), (200, {}, GOOD, 5.0)]) as (root, _),
            OperatorClient(CamaraConfig(api_root=root, timeout_s=0.3)) as operator,
        ):
            answer = await ConnectivityApi(operator).retrieve(
                ARENA, time.time() + 1, time.time() + 11, timeout_s=3
            )
            assert answer.status == GOOD["status"]
            started = time.monotonic()
            with pytest.raises(OperatorError) as hung:
                await ConnectivityApi(operator).retrieve(
                    ARENA, time.time() + 1, time.time() + 11, timeout_s=0.2
                )
            assert (hung.value.code, hung.value.message) == ("TIMEOUT", "no answer within 0.2 s")
            assert time.monotonic() - started < 1.0

    run(main())


@pytest.mark.parametrize(
    "body",
    [
        [],
        {"status": "SUPPORTED_AREA", "timedConnectivityData": []},  # no layerThickness
        {"layerThickness": 2, "status": "FINE", "timedConnectivityData": []},
        {"layerThickness": 2, "status": "SUPPORTED_AREA", "timedConnectivityData": [
            {"startTime": "2027-01-01T00:00:00Z", "endTime": "2027-01-01T00:10:00Z",
             "cellConnectivityData": [{"geohash": "u0p0581bs", "layerConnectivities": ["GOOD"]}]}]},
        {"layerThickness": 2, "status": "SUPPORTED_AREA", "timedConnectivityData": [
            {"startTime": "2027-01-01 00:00", "endTime": "2027-01-01T00:10:00Z",
             "cellConnectivityData": []}]},
        {"layerThickness": 2, "status": "OPERATION_NOT_COMPLETED", "statusInfo": "broke",
         "timedConnectivityData": []},
    ],
)  # fmt: skip
def test_an_answer_without_the_apis_shape_is_a_bad_response(body: Any) -> None:
    with pytest.raises(ValueError, match=r"\w"):  # each says what does not fit
        parse_prediction(body)

    async def main() -> None:
        async with (
            scripted([(200, {}, body, 0.0)]) as (root, _),
            OperatorClient(CamaraConfig(api_root=root)) as operator,
        ):
            with pytest.raises(OperatorError) as bad:
                await ConnectivityApi(operator).retrieve(ARENA, time.time() + 1, time.time() + 11)
            assert (bad.value.status, bad.value.code) == (502, "BAD_RESPONSE")

    run(main())
