"""The emulated operator's Predictive Connectivity Data (CAMARA 0.1.0), as pure logic.

A planner asks: for this polygon, these hours and this height above ground, which grid cells will carry
my service? A real operator answers from network data and models trained on it; this one answers from
the same radio map the cell flies (sim/network/radio.py) and the background load its timeline schedules,
with an error, so that the prediction is useful but not the truth: each cell's SINR is the map's at the
cell's centre and the layer's middle (not where the drone will be), plus a Gaussian error of
`error_db` drawn once per cell, layer and slot. A cell's level is GC when the rate it predicts for one
drone is at least `good_margin` times what the service level needs, MC at least what it needs, NC
below; ND outside the world's arena and above `max_height_m`. Where the API leaves a choice to the
implementation (slot length, layer thickness, geohash levels), the settings in [cell.prediction] make
it; docs/radio.md lists where the emulator simplifies.
"""

from __future__ import annotations

import math
import random
import zlib
from collections.abc import Sequence
from typing import Any

import pygeohash

from dynqos.common.camara import rfc3339, unix_time
from dynqos.common.config import CellConfig
from dynqos.common.config.radio import PredictionConfig
from dynqos.common.geo import Geo
from dynqos.sim.network.radio import Radio, RadioMap, efficiency

CODE = "PREDICTIVE_CONNECTIVITY_DATA"


class Refused(Exception):
    """A request the API answers with an error: its status, CAMARA code and message."""

    def __init__(self, status: int, code: str, message: str) -> None:
        super().__init__(message)
        self.status, self.code, self.message = status, code, message

    def __reduce__(self) -> tuple[type[Refused], tuple[int, str, str]]:  # raised in the prediction process
        return Refused, (self.status, self.code, self.message)


def parse_time(text: str, key: str) -> float:
    """An RFC 3339 date-time with its zone, as Unix seconds."""
    try:
        return unix_time(text)
    except ValueError:
        raise Refused(400, "INVALID_ARGUMENT", f"{key} is not an RFC 3339 date-time with a zone") from None


def _segments_cross(
    a: tuple[float, float], b: tuple[float, float], c: tuple[float, float], d: tuple[float, float]
) -> bool:
    def side(p: tuple[float, float], q: tuple[float, float], r: tuple[float, float]) -> float:
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    return side(a, b, c) * side(a, b, d) < 0 and side(c, d, a) * side(c, d, b) < 0


def simple_polygon(points: Sequence[tuple[float, float]]) -> bool:
    """No two edges that do not share a corner cross, and the polygon has an area."""
    n = len(points)
    edges = [(points[i], points[(i + 1) % n]) for i in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            if j in (i - 1, i + 1) or (i == 0 and j == n - 1):
                continue
            if _segments_cross(*edges[i], *edges[j]):
                return False
    return polygon_area(points) > 0


def polygon_area(points: Sequence[tuple[float, float]]) -> float:
    """The shoelace formula: the area a simple polygon's corners enclose."""
    return (
        abs(sum(p[0] * q[1] - q[0] * p[1] for p, q in zip(points, [*points[1:], points[0]], strict=True))) / 2
    )


def inside(point: tuple[float, float], polygon: Sequence[tuple[float, float]]) -> bool:
    """Ray casting."""
    x, y = point
    hit = False
    for (x1, y1), (x2, y2) in zip(polygon, [*polygon[1:], polygon[0]], strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            hit = not hit
    return hit


class Predictor:
    """Answers retrieve requests for one cell: its radio map, its arena, its scheduled background."""

    def __init__(
        self, radio_map: RadioMap, cell: CellConfig, arena_m: tuple[float, float], start_unix: float
    ) -> None:
        """`arena_m`: the world's size (x, y) around its origin, where the operator has data;
        `start_unix`: when the cell started (its timeline's zero)."""
        self.map = radio_map
        self.cell = cell
        self.config: PredictionConfig = cell.prediction
        self.geo = Geo(self.config.origin_lat_deg, self.config.origin_lon_deg)
        self.half = (arena_m[0] / 2, arena_m[1] / 2)
        self.start_unix = start_unix
        self.needs = {"C2": self.config.c2_mbps, "STREAM_4K": self.config.stream_4k_mbps}

    # ---- the schedule -------------------------------------------------------------------------------

    def background_weight(self, start_unix: float, end_unix: float) -> float:
        """The most weight of background users the cell's timeline has sending within the slot."""
        offered = {b.name: (b.offered_mbps, b.weight) for b in self.cell.background}
        events = sorted(
            (e for e in self.cell.events if e.kind == "background" and e.user in offered),
            key=lambda e: e.at_s,
        )
        start_s, end_s = start_unix - self.start_unix, end_unix - self.start_unix

        def weight() -> float:
            return sum(w for mbps, w in offered.values() if mbps > 0)

        i = 0
        while i < len(events) and events[i].at_s <= start_s:
            offered[events[i].user] = (events[i].offered_mbps, offered[events[i].user][1])
            i += 1
        worst = weight()
        while i < len(events) and events[i].at_s < end_s:
            offered[events[i].user] = (events[i].offered_mbps, offered[events[i].user][1])
            i += 1
            worst = max(worst, weight())
        return worst

    def rate_mbps(self, sinr_db: float, background_weight: float) -> float:
        """What one drone's uplink is predicted to carry in a slot: its share beside the scheduled
        background at its busiest (`background_weight`), at the efficiency of its SINR over the
        reference's."""
        reference = self.map.reference_efficiency
        factor = efficiency(sinr_db) / reference if reference else 0.0
        return self.cell.uplink_mbps * factor / (1.0 + background_weight)

    def level(self, rate_mbps: float, need_mbps: float) -> str:
        if rate_mbps >= self.config.good_margin * need_mbps:
            return "GC"
        return "MC" if rate_mbps >= need_mbps else "NC"

    # ---- one request ----------------------------------------------------------------------------------

    def retrieve(self, request: dict[str, Any], now_unix: float) -> dict[str, Any]:
        """The ConnectivityDataResponse for a request the schema already accepted; Refused otherwise."""
        c = self.config
        if request.get("sink"):
            raise Refused(
                422, f"{CODE}.UNSUPPORTED_REQUEST", "this operator answers synchronously only: no sink"
            )
        precision = int(request.get("precision", 7))
        if precision not in c.precisions:
            levels = ", ".join(map(str, c.precisions))
            raise Refused(
                422,
                f"{CODE}.UNSUPPORTED_PRECISION",
                "Indicated cell precision (Geohash level) is "
                f"not supported: this operator answers levels {levels}",
            )
        start = parse_time(request["startTime"], "startTime")
        end = parse_time(request["endTime"], "endTime")
        self._check_times(start, end, now_unix)
        boundary = [(p["latitude"], p["longitude"]) for p in request["area"]["boundary"]]
        if not simple_polygon(boundary):
            raise Refused(
                400, f"{CODE}.INVALID_AREA", "The area is not a polygon shape or has an arbitrary complexity"
            )
        cells = self._cells(boundary, precision)
        height = request.get("height")
        layers = self._layers(height)
        slots = self._slots(start, end)
        if len(cells) * len(layers) * len(slots) > c.max_values:
            raise Refused(
                422,
                f"{CODE}.UNSUPPORTED_REQUEST",
                "The indicated request is too big for both synchronous and asynchronous processing",
            )
        places = {gh: self._place(gh) for gh in cells}  # each cell's centre in local metres, decoded once
        supported = [self.covers(*places[gh]) for gh in cells]
        status = "SUPPORTED_AREA" if all(supported) else "PART_OF_AREA_NOT_SUPPORTED"
        if not any(supported):
            status = "AREA_NOT_SUPPORTED"
        need = self.needs[request["serviceLevel"]]
        signal = bool(request.get("includeSignalStrength", False))
        timed = []
        if status != "AREA_NOT_SUPPORTED":
            nowhere: list[Radio | None] = [None] * len(layers)
            radios = {  # the map at each cell's centre and layer's middle: the same in every slot
                gh: self._radios(places[gh], layers) if ok else nowhere
                for gh, ok in zip(cells, supported, strict=True)
            }
            for slot_start, slot_end in slots:
                weight = self.background_weight(slot_start, slot_end)
                rows = [self._cell(gh, layers, radios[gh], slot_start, weight, need, signal) for gh in cells]
                timed.append(
                    {
                        "startTime": rfc3339(slot_start),
                        "endTime": rfc3339(slot_end),
                        "cellConnectivityData": rows,
                    }
                )
        answer: dict[str, Any] = {
            "layerThickness": c.layer_thickness_m,
            "timedConnectivityData": timed,
            "status": status,
        }
        if height is not None:
            answer["requestedHeight"] = int(height)
        return answer

    def _check_times(self, start: float, end: float, now: float) -> None:
        c = self.config
        if end <= start:
            raise Refused(400, f"{CODE}.INVALID_END_TIME", "Indicated endTime is earlier than the startTime")
        if start < now - 1.0:
            if end > now:
                raise Refused(
                    400,
                    f"{CODE}.INVALID_TIME_PERIOD",
                    "time period is partially in the past and partially in the future",
                )
            raise Refused(
                400,
                f"{CODE}.MIN_STARTTIME_EXCEEDED",
                "Indicated startTime is earlier than the "
                "minimum allowed: this operator predicts, it does not report the past",
            )
        if start > now + c.horizon_s:
            raise Refused(
                400,
                f"{CODE}.MAX_STARTTIME_EXCEEDED",
                f"Indicated startTime is greater than the maximum allowed ({c.horizon_s:g} s ahead)",
            )
        if end - start > c.max_period_s:
            raise Refused(
                400,
                f"{CODE}.MAX_TIME_PERIOD_EXCEEDED",
                f"Indicated time period is greater than the maximum allowed ({c.max_period_s:g} s)",
            )

    def _cells(self, boundary: list[tuple[float, float]], precision: int) -> list[str]:
        """The geohash cells of `precision` whose centre is inside the polygon, south-west first."""
        lats, lons = [p[0] for p in boundary], [p[1] for p in boundary]
        box = pygeohash.BoundingBox(min(lats), min(lons), max(lats), max(lons))
        found = []
        for gh in sorted(set(pygeohash.geohashes_in_box(box, precision=precision))):
            centre = pygeohash.decode_exactly(gh)
            if inside((centre.latitude, centre.longitude), boundary):
                found.append(gh)
        return found

    def _layers(self, height: Any) -> list[int]:
        c = self.config
        count = max(1, math.ceil(c.max_height_m / c.layer_thickness_m))
        if height is None:
            return list(range(count))
        return [int(height // c.layer_thickness_m)]

    def _slots(self, start: float, end: float) -> list[tuple[float, float]]:
        step = self.config.slot_s
        first = math.floor(start / step) * step
        return [(t, t + step) for t in (first + i * step for i in range(math.ceil((end - first) / step)))]

    def covers(self, x: float, y: float) -> bool:
        """Is the local (x, y) where the operator has data (the world's arena)?"""
        return abs(x) <= self.half[0] and abs(y) <= self.half[1]

    def _place(self, gh: str) -> tuple[float, float]:
        centre = pygeohash.decode_exactly(gh)
        return self.geo.to_local(centre.latitude, centre.longitude)

    def _radios(self, place: tuple[float, float], layers: list[int]) -> list[Radio | None]:
        """The map at the cell's centre in the middle of each layer; None above `max_height_m`."""
        c = self.config
        out: list[Radio | None] = []
        for layer in layers:
            middle_m = (layer + 0.5) * c.layer_thickness_m
            out.append(None if middle_m > c.max_height_m else self.map.at((place[0], place[1], -middle_m)))
        return out

    def _cell(
        self,
        gh: str,
        layers: list[int],
        radios: list[Radio | None],
        slot_start: float,
        weight: float,
        need: float,
        signal: bool,
    ) -> dict[str, Any]:
        c = self.config
        levels: list[str] = []
        strengths: list[float | None] = []
        for layer, radio in zip(layers, radios, strict=True):
            if radio is None:
                levels.append("ND")
                strengths.append(None)
                continue
            seed = zlib.crc32(f"{c.seed}:{gh}:{layer}:{int(slot_start)}".encode())
            error = random.Random(seed).gauss(0.0, c.error_db) if c.error_db > 0 else 0.0
            levels.append(self.level(self.rate_mbps(radio.sinr_db + error, weight), need))
            strengths.append(round(radio.rsrp_dbm + error, 1))
        row: dict[str, Any] = {"geohash": gh, "layerConnectivities": levels}
        if signal:
            row["layerSignalStrengths"] = strengths
        return row
