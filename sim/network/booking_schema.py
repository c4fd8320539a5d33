"""JSON Schemas of CAMARA QoS Booking 0.1.0's requests, as the emulated operator takes them: written from
`CreateBooking` and `RetrieveBookingByDevice` of the spec (camaraproject/QoSBooking, release r1.2) with
their required fields, types, enums and bounds, closed to fields the API does not have (a request that
does not fit is a 400 INVALID_ARGUMENT)."""

from __future__ import annotations

from typing import Any

from dynqos.sim.network.operator_schema import (
    _BASE,
    _DATE_TIME,
    APPLICATION_SERVER,
    DEVICE,
    PORTS_SPEC,
    QOS_PROFILE,
    SINK_CREDENTIAL,
    _closed,
)
from dynqos.sim.network.prediction_schema import POINT

AREA: dict[str, Any] = {
    "type": "object",
    "required": ["areaType"],
    "properties": {"areaType": {"enum": ["CIRCLE", "POLYGON", "AREANAME"]}},
    "oneOf": [
        {
            "properties": {
                "areaType": {"const": "CIRCLE"},
                "center": POINT,
                "radius": {"type": "number", "minimum": 1},
            },
            "required": ["center", "radius"],
            "additionalProperties": False,
        },
        {
            "properties": {
                "areaType": {"const": "POLYGON"},
                "boundary": {"type": "array", "minItems": 3, "maxItems": 15, "items": POINT},
            },
            "required": ["boundary"],
            "additionalProperties": False,
        },
        {
            "properties": {"areaType": {"const": "AREANAME"}, "areaName": {"type": "string"}},
            "required": ["areaName"],
            "additionalProperties": False,
        },
    ],
}
CREATE_BOOKING: dict[str, Any] = {
    "type": "object",
    "required": ["qosProfile", "startTime", "duration", "serviceArea"],
    "properties": {
        "device": DEVICE,
        "applicationServer": APPLICATION_SERVER,
        "devicePorts": PORTS_SPEC,
        "applicationServerPorts": PORTS_SPEC,
        "qosProfile": QOS_PROFILE,
        "startTime": {"type": "string", "pattern": _DATE_TIME},
        "duration": {"type": "integer", "minimum": 1, "maximum": 2**31 - 1},
        "serviceArea": AREA,
        "sink": _BASE["sink"],  # https, or http on loopback for the demo, as on the QoD API
        "sinkCredential": SINK_CREDENTIAL,
    },
}
RETRIEVE_BOOKINGS: dict[str, Any] = {"type": "object", "properties": {"device": DEVICE}}
CREATE_BOOKING_STRICT: dict[str, Any] = _closed(CREATE_BOOKING, (SINK_CREDENTIAL, AREA))
RETRIEVE_BOOKINGS_STRICT: dict[str, Any] = _closed(RETRIEVE_BOOKINGS, ())
