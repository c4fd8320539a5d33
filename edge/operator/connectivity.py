"""The edge's client of CAMARA Predictive Connectivity Data (0.1.0): what the network predicts a drone's
link will carry, by grid cell, height layer and time slot, so that a planner can route and schedule by it.

Calls go through the operator client (edge/operator/client.py): the same token (the agent's scopes
include `predictive-connectivity-data:read`), x-correlator, retries of 429 and 5xx with back-off within
the call's time-out, and an OperatorError that names the API's code. An answer that does not have the API's
shape is an OperatorError too (502 BAD_RESPONSE): a planner never plans on half an answer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pygeohash

from dynqos.common.camara import rfc3339, unix_time
from dynqos.common.config import CamaraConfig
from dynqos.common.geo import Geo
from dynqos.edge.operator.client import OperatorClient, OperatorError, beside

LEVELS = ("GC", "MC", "NC", "ND")
STATUSES = ("SUPPORTED_AREA", "PART_OF_AREA_NOT_SUPPORTED", "AREA_NOT_SUPPORTED", "OPERATION_NOT_COMPLETED")


@dataclass(frozen=True, slots=True)
class CellPrediction:
    levels: tuple[str, ...]  # one per layer from the ground (or the requested height's only)
    rsrp_dbm: tuple[float | None, ...] = ()  # the same layers' predicted signal, when asked for


@dataclass(frozen=True, slots=True)
class Slot:
    start_unix: float
    end_unix: float
    cells: dict[str, CellPrediction]  # geohash -> prediction


@dataclass(frozen=True, slots=True)
class Prediction:
    status: str
    layer_thickness_m: float
    slots: tuple[Slot, ...]
    requested_height_m: int | None = None

    def level(self, geohash: str, unix_s: float, layer: int = 0) -> str:
        """The level predicted for a cell at a time and layer: ND where the answer says nothing."""
        for slot in self.slots:
            if slot.start_unix <= unix_s < slot.end_unix:
                cell = slot.cells.get(geohash)
                if cell is None:
                    return "ND"
                index = 0 if self.requested_height_m is not None else layer
                return cell.levels[index] if index < len(cell.levels) else "ND"
        return "ND"


def connectivity_root(cfg: CamaraConfig) -> str:
    """`connectivity_root`, or beside the QoD API ({apiRoot}/predictive-connectivity-data/v0.1)."""
    return beside(cfg, cfg.connectivity_root, "predictive-connectivity-data/v0.1")


def parse_prediction(body: Any) -> Prediction:
    """A ConnectivityDataResponse, checked; ValueError saying what does not fit."""
    if not isinstance(body, dict):
        raise ValueError("the answer is not an object")
    status = body.get("status")
    if status not in STATUSES:
        raise ValueError(f"status {status!r} is none of the API's")
    if status == "OPERATION_NOT_COMPLETED":
        raise ValueError(f"the operator could not complete it: {str(body.get('statusInfo', ''))[:200]}")
    thickness = body.get("layerThickness")
    if not isinstance(thickness, (int, float)) or not thickness > 0:
        raise ValueError("layerThickness is not a positive number")
    slots = []
    for item in body.get("timedConnectivityData") or []:
        cells = {}
        for row in item.get("cellConnectivityData") or []:
            levels = row.get("layerConnectivities")
            if not isinstance(row.get("geohash"), str) or not isinstance(levels, list) or not levels:
                raise ValueError("a cell has no geohash or no layerConnectivities")
            if any(level not in LEVELS for level in levels):
                raise ValueError(f"a cell's levels {levels[:8]} are not all of {LEVELS}")
            strengths = row.get("layerSignalStrengths") or []
            if any(s is not None and not isinstance(s, (int, float)) for s in strengths):
                raise ValueError("a signal strength is not a number")
            cells[row["geohash"]] = CellPrediction(tuple(levels), tuple(strengths))
        slots.append(Slot(unix_time(item.get("startTime")), unix_time(item.get("endTime")), cells))
    height = body.get("requestedHeight")
    return Prediction(status, float(thickness), tuple(slots), int(height) if height is not None else None)


class ConnectivityApi:
    """Predictive Connectivity Data over an open OperatorClient."""

    def __init__(self, operator: OperatorClient) -> None:
        self.operator = operator
        self.root = connectivity_root(operator.cfg)

    async def retrieve(
        self,
        boundary: list[tuple[float, float]],
        start_unix: float,
        end_unix: float,
        *,
        service_level: str = "C2",
        precision: int = 7,
        height_m: int | None = None,
        signal_strength: bool = False,
        timeout_s: float | None = None,
    ) -> Prediction:
        """The prediction for a polygon of (latitude, longitude) corners over [start, end) (`timeout_s`:
        this call's time-out, in place of the client's)."""
        body: dict[str, Any] = {
            "serviceLevel": service_level,
            "area": {
                "areaType": "POLYGON",
                "boundary": [{"latitude": a, "longitude": o} for a, o in boundary],
            },
            "startTime": rfc3339(start_unix),
            "endTime": rfc3339(end_unix),
            "precision": precision,
        }
        if height_m is not None:
            body["height"] = height_m
        if signal_strength:
            body["includeSignalStrength"] = True
        answer = await self.operator.request(
            "POST", "/retrieve", body, expect=(200,), root=self.root, timeout_s=timeout_s
        )
        try:
            return parse_prediction(answer)
        except ValueError as exc:
            raise OperatorError(502, "BAD_RESPONSE", f"predictive connectivity: {exc}") from None


class PredictedLevels:
    """A prediction read the way the fleet planner asks (edge/planner/fleet_plan.py, `Connectivity`):
    the level at local (x, y) metres, a height above ground and seconds from `start_unix`."""

    def __init__(self, prediction: Prediction, geo: Geo, start_unix: float, precision: int) -> None:
        self.prediction = prediction
        self.geo = geo
        self.start_unix = start_unix
        self.precision = precision

    def level(self, x: float, y: float, height_m: float, t_s: float) -> str:
        cell = pygeohash.encode(*self.geo.to_latlon(x, y), precision=self.precision)
        layer = int(height_m // self.prediction.layer_thickness_m)
        return self.prediction.level(cell, self.start_unix + t_s, layer)
