"""JSON Schema of CAMARA Predictive Connectivity Data 0.1.0's retrieve request, as the emulated operator
takes it: written from `RetrieveConnectivityRequest` of the spec (camaraproject/PredictiveConnectivityData,
release r1.2) with its required fields, types, enums and bounds, closed to fields the API does not have
(a request that does not fit is a 400 INVALID_ARGUMENT)."""

from __future__ import annotations

from typing import Any

from dynqos.sim.network.operator_schema import _DATE_TIME, SINK_CREDENTIAL, _closed

POINT: dict[str, Any] = {
    "type": "object",
    "required": ["latitude", "longitude"],
    "properties": {
        "latitude": {"type": "number", "minimum": -90, "maximum": 90},
        "longitude": {"type": "number", "minimum": -180, "maximum": 180},
    },
}
RETRIEVE_CONNECTIVITY: dict[str, Any] = {
    "type": "object",
    "required": ["serviceLevel", "area", "startTime", "endTime"],
    "properties": {
        "serviceLevel": {"enum": ["C2", "STREAM_4K"]},
        "area": {
            "type": "object",
            "required": ["areaType", "boundary"],
            "properties": {
                "areaType": {"enum": ["POLYGON"]},
                "boundary": {"type": "array", "minItems": 3, "maxItems": 15, "items": POINT},
            },
        },
        "startTime": {"type": "string", "pattern": _DATE_TIME},
        "endTime": {"type": "string", "pattern": _DATE_TIME},
        "networkType": {"enum": ["4G", "5G"]},
        "precision": {"type": "integer", "minimum": 1, "maximum": 12},
        "height": {"type": "integer", "minimum": 0, "maximum": 250},
        "includeSignalStrength": {"type": "boolean"},
        "sink": {"type": "string", "pattern": r"^https:\/\/.+$"},
        "sinkCredential": SINK_CREDENTIAL,
    },
}
RETRIEVE_CONNECTIVITY_STRICT: dict[str, Any] = _closed(RETRIEVE_CONNECTIVITY, (SINK_CREDENTIAL,))
