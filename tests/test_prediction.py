"""The emulated operator's Predictive Connectivity Data (sim/network/prediction.py), pure: cells from a
polygon, layers, slots, levels from the radio map and the scheduled background, and every refusal the
API defines. The answers are checked against the official CAMARA document where it is present."""

from __future__ import annotations

import datetime as dt
from typing import Any

import pygeohash
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dynqos.common.config import (
    BackgroundConfig,
    CellConfig,
    CellEventConfig,
    CoverageHoleConfig,
    PredictionConfig,
    RadioConfig,
)
from dynqos.common.geo import Geo
from dynqos.sim.network.operator_schema import problem
from dynqos.sim.network.prediction import Predictor, Refused, inside, rfc3339, simple_polygon
from dynqos.sim.network.prediction_schema import RETRIEVE_CONNECTIVITY_STRICT
from dynqos.sim.network.radio import RadioMap
from dynqos.sim.vehicle.world import World
from tests import camara_spec

NOW = 1_800_000_000.0  # a fixed wall clock (2027-01-15)
HOLE = CoverageHoleConfig(center_m=(10.0, 10.0), radius_m=4.0, edge_m=0.0, loss_db=60.0, top_m=3.0)


def predictor(error_db: float = 0.0, max_values: int = 200_000, **cell: Any) -> Predictor:
    radio = RadioConfig(enabled=True, holes=(HOLE,))
    prediction = PredictionConfig(error_db=error_db, max_values=max_values)
    config = CellConfig(radio=radio, prediction=prediction, **cell)
    return Predictor(RadioMap(radio, World()), config, (40.0, 40.0), start_unix=NOW)


def square(geo: Geo, x0: float, y0: float, x1: float, y1: float) -> list[dict[str, float]]:
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return [dict(zip(("latitude", "longitude"), geo.to_latlon(x, y), strict=True)) for x, y in corners]


def request(p: Predictor, **changes: Any) -> dict[str, Any]:
    body = {
        "serviceLevel": "STREAM_4K",
        "area": {"areaType": "POLYGON", "boundary": square(p.geo, -20, -20, 20, 20)},
        "startTime": rfc3339(NOW + 5),
        "endTime": rfc3339(NOW + 25),
        "precision": 9,
        **changes,
    }
    assert problem(RETRIEVE_CONNECTIVITY_STRICT, body) is None
    return body


def spec_check(body: dict[str, Any], answer: dict[str, Any]) -> None:
    if camara_spec.available():
        return
    path = "/predictive-connectivity-data/v0.1/retrieve"
    assert camara_spec.problems("POST", path, body, 200, answer) == []


def test_the_local_frame_and_the_globe_agree() -> None:
    geo = Geo(45.0, 10.0)
    lat, lon = geo.to_latlon(100.0, -50.0)
    assert lat > 45.0
    assert lon < 10.0
    x, y = geo.to_local(lat, lon)
    assert (x, y) == pytest.approx((100.0, -50.0), abs=1e-6)


def test_polygons_cells_layers_and_slots() -> None:
    p = predictor()
    body = request(p, includeSignalStrength=True)
    answer = p.retrieve(body, NOW)
    spec_check(body, answer)
    assert answer["status"] == "SUPPORTED_AREA"
    assert answer["layerThickness"] == 2.0
    slots = answer["timedConnectivityData"]
    assert [(s["startTime"], s["endTime"]) for s in slots] == [
        (rfc3339(NOW), rfc3339(NOW + 10)), (rfc3339(NOW + 10), rfc3339(NOW + 20)),
        (rfc3339(NOW + 20), rfc3339(NOW + 30)),
    ]  # fmt: skip
    cells = slots[0]["cellConnectivityData"]
    assert len(cells) > 40  # a 40 m square in ~4.8 x 3.4 m cells
    assert {len(c["geohash"]) for c in cells} == {9}
    assert all(len(c["layerConnectivities"]) == 4 == len(c["layerSignalStrengths"]) for c in cells)
    for c in cells:  # every centre inside the square
        centre = pygeohash.decode_exactly(c["geohash"])
        x, y = p.geo.to_local(centre.latitude, centre.longitude)
        assert abs(x) <= 20.5
        assert abs(y) <= 20.5


def test_a_hole_is_predicted_where_it_is_and_only_below_its_top() -> None:
    p = predictor()
    answer = p.retrieve(request(p), NOW)
    levels = {}
    for c in answer["timedConnectivityData"][0]["cellConnectivityData"]:
        centre = pygeohash.decode_exactly(c["geohash"])
        levels[p.geo.to_local(centre.latitude, centre.longitude)] = c["layerConnectivities"]
    in_hole = [lv for (x, y), lv in levels.items() if (x - 10) ** 2 + (y - 10) ** 2 < 3**2]
    far = [lv for (x, y), lv in levels.items() if (x - 10) ** 2 + (y - 10) ** 2 > 8**2]
    assert in_hole
    assert all(lv[0] == "NC" and lv[1] == "NC" for lv in in_hole)  # 0-2 m and 2-4 m (middle 3 m: the top)
    assert all(lv[2] != "NC" for lv in in_hole)  # 4-6 m is above the hole
    assert all(lv[0] == "GC" for lv in far)  # an empty cell carries 4K twice over


def test_the_scheduled_background_lowers_the_level_in_its_slots() -> None:
    loaded = predictor(
        background=(BackgroundConfig(name="bg", weight=5.0),),
        events=(CellEventConfig(at_s=15.0, kind="background", user="bg", offered_mbps=80.0),),
    )
    answer = loaded.retrieve(request(loaded), NOW)
    before, during = (
        [c["layerConnectivities"][0] for c in s["cellConnectivityData"]]
        for s in (answer["timedConnectivityData"][0], answer["timedConnectivityData"][2])
    )
    assert before.count("GC") > during.count("GC")
    assert during.count("GC") == 0  # 81.3 / 6 = 13.6 Mbit/s: not 25


def test_the_error_is_seeded_and_moves_some_cells_but_not_the_hole() -> None:
    exact, noisy = predictor(0.0), predictor(6.0)
    a = exact.retrieve(request(exact, serviceLevel="STREAM_4K"), NOW)
    b = noisy.retrieve(request(noisy, serviceLevel="STREAM_4K"), NOW)
    assert b == noisy.retrieve(request(noisy, serviceLevel="STREAM_4K"), NOW)  # the same answer again
    differ = sum(
        x != y
        for ca, cb in zip(
            a["timedConnectivityData"][0]["cellConnectivityData"],
            b["timedConnectivityData"][0]["cellConnectivityData"],
            strict=True,
        )
        for x, y in zip(ca["layerConnectivities"], cb["layerConnectivities"], strict=True)
    )
    assert differ > 0


def test_a_height_answers_its_layer_only_and_is_echoed() -> None:
    p = predictor()
    body = request(p, height=5)
    answer = p.retrieve(body, NOW)
    spec_check(body, answer)
    assert answer["requestedHeight"] == 5
    assert {
        len(c["layerConnectivities"]) for c in answer["timedConnectivityData"][0]["cellConnectivityData"]
    } == {1}
    high = p.retrieve(request(p, height=100), NOW)
    assert {
        c["layerConnectivities"][0] for c in high["timedConnectivityData"][0]["cellConnectivityData"]
    } == {"ND"}


def test_outside_the_arena_there_is_no_data() -> None:
    p = predictor()
    part = p.retrieve(
        request(p, area={"areaType": "POLYGON", "boundary": square(p.geo, 10, 10, 40, 40)}), NOW
    )
    assert part["status"] == "PART_OF_AREA_NOT_SUPPORTED"
    rows = part["timedConnectivityData"][0]["cellConnectivityData"]
    assert any(set(r["layerConnectivities"]) == {"ND"} for r in rows)
    assert any("ND" not in r["layerConnectivities"] for r in rows)
    body = request(p, area={"areaType": "POLYGON", "boundary": square(p.geo, 100, 100, 140, 140)})
    away = p.retrieve(body, NOW)
    spec_check(body, away)
    assert away == {"layerThickness": 2.0, "timedConnectivityData": [], "status": "AREA_NOT_SUPPORTED"}


@pytest.mark.parametrize(
    ("changes", "status", "code"),
    [
        ({"precision": 7}, 422, "UNSUPPORTED_PRECISION"),
        ({"endTime": rfc3339(NOW + 1), "startTime": rfc3339(NOW + 5)}, 400, "INVALID_END_TIME"),
        ({"startTime": rfc3339(NOW - 60), "endTime": rfc3339(NOW - 30)}, 400, "MIN_STARTTIME_EXCEEDED"),
        ({"startTime": rfc3339(NOW - 60), "endTime": rfc3339(NOW + 30)}, 400, "INVALID_TIME_PERIOD"),
        ({"startTime": rfc3339(NOW + 7200), "endTime": rfc3339(NOW + 7300)}, 400, "MAX_STARTTIME_EXCEEDED"),
        ({"endTime": rfc3339(NOW + 4000)}, 400, "MAX_TIME_PERIOD_EXCEEDED"),
        ({"sink": "https://example.com/sink"}, 422, "UNSUPPORTED_REQUEST"),
        ({"precision": 8, "endTime": rfc3339(NOW + 3600)}, 422, "UNSUPPORTED_REQUEST"),  # 360 slots x 4
    ],
)
def test_refusals_carry_the_apis_codes(changes: dict[str, Any], status: int, code: str) -> None:
    p = predictor(max_values=2000)
    with pytest.raises(Refused) as refused:
        p.retrieve(request(p, **changes), NOW)
    assert (refused.value.status, refused.value.code) == (status, f"PREDICTIVE_CONNECTIVITY_DATA.{code}")


def test_a_self_crossing_polygon_is_an_invalid_area() -> None:
    p = predictor()
    bow = square(p.geo, -10, -10, 10, 10)
    bow[1], bow[2] = bow[2], bow[1]  # a bow tie
    with pytest.raises(Refused) as refused:
        p.retrieve(request(p, area={"areaType": "POLYGON", "boundary": bow}), NOW)
    assert refused.value.code == "PREDICTIVE_CONNECTIVITY_DATA.INVALID_AREA"


def test_requests_outside_the_schema_are_found() -> None:
    p = predictor()
    assert problem(RETRIEVE_CONNECTIVITY_STRICT, {**request(p), "serviceLevel": "VIDEO"})
    assert problem(RETRIEVE_CONNECTIVITY_STRICT, {**request(p), "colour": "red"})
    assert problem(RETRIEVE_CONNECTIVITY_STRICT, {**request(p), "height": 300})
    two = request(p)
    two["area"] = {"areaType": "POLYGON", "boundary": two["area"]["boundary"][:2]}
    assert problem(RETRIEVE_CONNECTIVITY_STRICT, two)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=3, max_size=8))
def test_a_point_inside_a_simple_polygon_is_inside_its_bounding_box(
    points: list[tuple[float, float]],
) -> None:
    if not simple_polygon(points):
        return
    cx = sum(p[0] for p in points) / len(points)
    cy = sum(p[1] for p in points) / len(points)
    if inside((cx, cy), points):
        assert min(p[0] for p in points) <= cx <= max(p[0] for p in points)
        assert min(p[1] for p in points) <= cy <= max(p[1] for p in points)


def test_time_stamps_are_rfc3339_utc() -> None:
    assert rfc3339(0) == "1970-01-01T00:00:00Z"
    assert dt.datetime.fromisoformat(rfc3339(NOW).replace("Z", "+00:00")).timestamp() == NOW
