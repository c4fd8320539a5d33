"""JSON Schemas of the CAMARA Quality-on-Demand v1.1.0 objects dynqos sends and serves.

Written from the field set of the spec (`code/API_definitions/quality-on-demand.yaml` in
camaraproject/QualityOnDemand, release r3.2): required fields, types, enums and patterns. The emulated
operator validates every request body with them (a bad one is a 400 INVALID_ARGUMENT, as an operator
answers); the tests validate what the client sends and what the emulator answers with the same schemas.
"""

from __future__ import annotations

from typing import Any

import jsonschema

from dynqos.common.camara import EVENT_TYPE, QOS_STATUS, STATUS_INFO

_IPV4 = r"^(25[0-5]|2[0-4][0-9]|1?[0-9]?[0-9])(\.(25[0-5]|2[0-4][0-9]|1?[0-9]?[0-9])){3}$"
_IPV4_OR_CIDR = _IPV4[:-1] + r"(/([0-9]|[12][0-9]|3[0-2]))?$"
_UUID = r"^[0-9a-fA-F]{8}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{12}$"
_DATE_TIME = r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d+)?(Z|[+-]\d{2}:\d{2})$"  # RFC 3339, with a zone

PORT: dict[str, Any] = {"type": "integer", "minimum": 0, "maximum": 65535}
PORTS_SPEC: dict[str, Any] = {
    "type": "object",
    "minProperties": 1,
    "properties": {
        "ranges": {
            "type": "array",
            "minItems": 1,
            "items": {
                "type": "object",
                "required": ["from", "to"],
                "properties": {"from": PORT, "to": PORT},
            },
        },
        "ports": {"type": "array", "minItems": 1, "items": PORT},
    },
}
DEVICE: dict[str, Any] = {
    "type": "object",
    "minProperties": 1,
    "properties": {
        "phoneNumber": {"type": "string", "pattern": r"^\+[1-9][0-9]{4,14}$"},
        "networkAccessIdentifier": {"type": "string"},
        "ipv4Address": {
            "type": "object",
            "properties": {
                "publicAddress": {"type": "string", "pattern": _IPV4},
                "privateAddress": {"type": "string", "pattern": _IPV4},
                "publicPort": PORT,
            },
            "anyOf": [
                {"required": ["publicAddress", "privateAddress"]},
                {"required": ["publicAddress", "publicPort"]},
            ],
        },
        "ipv6Address": {"type": "string"},
    },
}
APPLICATION_SERVER: dict[str, Any] = {
    "type": "object",
    "minProperties": 1,
    "properties": {
        "ipv4Address": {"type": "string", "pattern": _IPV4_OR_CIDR},
        "ipv6Address": {"type": "string"},
    },
}
# Quality-on-Demand 1.2.0 (camaraproject/QualityOnDemand r4.1, 1.2.0-rc.3: ApplicationServer,
# ApplicationServerIpAddressList, ApplicationServerIpAddressSubnets): the server is named either by a
# list of single addresses or by the subnets of 1.1.0, one form or the other (oneOf), each closed.
_SINGLE_IP = {
    "anyOf": [{"type": "string", "pattern": _IPV4}, {"type": "string", "pattern": r"^[0-9a-fA-F:.]+$"}]
}
APPLICATION_SERVER_1_2: dict[str, Any] = {
    "oneOf": [
        {
            "type": "object",
            "required": ["ipAddresses"],
            "additionalProperties": False,
            "properties": {
                "ipAddresses": {
                    "type": "array",
                    "minItems": 1,
                    "maxItems": 16,
                    "uniqueItems": True,
                    "items": _SINGLE_IP,
                },
            },
        },
        {**APPLICATION_SERVER, "maxProperties": 2, "additionalProperties": False},
    ]
}
QOS_PROFILE: dict[str, Any] = {
    "type": "string",
    "minLength": 3,
    "maxLength": 256,
    "pattern": r"^[a-zA-Z0-9_.-]+$",
}
SINK_CREDENTIAL: dict[str, Any] = {
    "type": "object",
    "required": ["credentialType"],
    "properties": {"credentialType": {"enum": ["PLAIN", "ACCESSTOKEN", "REFRESHTOKEN"]}},
}
_BASE = {
    "device": DEVICE,
    "applicationServer": APPLICATION_SERVER,
    "devicePorts": PORTS_SPEC,
    "applicationServerPorts": PORTS_SPEC,
    "qosProfile": QOS_PROFILE,
    "sink": {
        "type": "string",
        "pattern": r"^(https://.+|http://(127\.[0-9.]+|localhost|\[::1\])(:[0-9]+)?(/.*)?)$",
    },  # the spec says https; the emulator also takes http on loopback, for the demo (docs/qos.md)
    "sinkCredential": SINK_CREDENTIAL,
}
CREATE_SESSION: dict[str, Any] = {
    "type": "object",
    "required": ["applicationServer", "qosProfile", "duration"],
    "properties": {**_BASE, "duration": {"type": "integer", "minimum": 1, "maximum": 2**31 - 1}},
}
SESSION_INFO: dict[str, Any] = {
    "type": "object",
    "required": ["sessionId", "duration", "qosStatus", "applicationServer", "qosProfile"],
    "properties": {
        **_BASE,
        "device": {**DEVICE, "maxProperties": 1},
        "sessionId": {"type": "string", "pattern": _UUID},
        "duration": {"type": "integer", "minimum": 1},
        "startedAt": {"type": "string", "pattern": _DATE_TIME},
        "expiresAt": {"type": "string", "pattern": _DATE_TIME},
        "qosStatus": {"enum": list(QOS_STATUS)},
        "statusInfo": {"enum": list(STATUS_INFO)},
    },
    # startedAt and expiresAt are not returned while REQUESTED
    "if": {"properties": {"qosStatus": {"const": "REQUESTED"}}},
    "then": {"not": {"anyOf": [{"required": ["startedAt"]}, {"required": ["expiresAt"]}]}},
}
EXTEND_SESSION: dict[str, Any] = {
    "type": "object",
    "required": ["requestedAdditionalDuration"],
    "properties": {"requestedAdditionalDuration": {"type": "integer", "minimum": 1, "maximum": 2**31 - 1}},
}
RETRIEVE_SESSIONS: dict[str, Any] = {"type": "object", "properties": {"device": DEVICE}}
RETRIEVE_SESSIONS_OUTPUT: dict[str, Any] = {"type": "array", "items": SESSION_INFO}
# qos-profiles v1.1.0's QosProfileDeviceRequest (retrieve-qos-profiles)
RETRIEVE_PROFILES: dict[str, Any] = {
    "type": "object",
    "properties": {
        "device": DEVICE,
        "name": {"type": "string", "minLength": 3, "maxLength": 256, "pattern": "^[a-zA-Z0-9_.-]+$"},
        "status": {"enum": ["ACTIVE", "INACTIVE", "DEPRECATED"]},
    },
}
ERROR_INFO: dict[str, Any] = {
    "type": "object",
    "required": ["status", "code", "message"],
    "properties": {"status": {"type": "integer"}, "code": {"type": "string"}, "message": {"type": "string"}},
}
QOS_STATUS_CHANGED: dict[str, Any] = {
    "type": "object",
    "required": ["id", "source", "specversion", "type", "time", "data"],
    "properties": {
        "id": {"type": "string"},
        "source": {"type": "string"},
        "specversion": {"const": "1.0"},
        "type": {"const": EVENT_TYPE},
        "datacontenttype": {"const": "application/json"},
        "time": {"type": "string", "pattern": _DATE_TIME},
        "data": {
            "type": "object",
            "required": ["sessionId", "qosStatus"],
            "properties": {
                "sessionId": {"type": "string", "pattern": _UUID},
                "qosStatus": {"enum": ["AVAILABLE", "UNAVAILABLE"]},
                "statusInfo": {"enum": list(STATUS_INFO)},
            },
        },
    },
}


def _closed(schema: Any, keep_open: tuple[Any, ...]) -> Any:
    """A copy of `schema` where every object with `properties` takes no others (additionalProperties
    false), except the schemas in `keep_open`: a request with a field the API does not have is a 400."""
    if isinstance(schema, list):
        return [_closed(item, keep_open) for item in schema]
    if not isinstance(schema, dict) or any(schema is k for k in keep_open):
        return schema
    out = {key: _closed(value, keep_open) for key, value in schema.items()}
    if "properties" in out:
        out["additionalProperties"] = False
    return out


# What the emulated operator takes: the request objects, closed. The sink credential stays open (its
# fields depend on credentialType, and the emulator reads only the token from it).
CREATE_SESSION_STRICT: dict[str, Any] = _closed(CREATE_SESSION, (SINK_CREDENTIAL,))
CREATE_SESSION_STRICT_1_2: dict[str, Any] = {
    **CREATE_SESSION_STRICT,
    "properties": {**CREATE_SESSION_STRICT["properties"], "applicationServer": APPLICATION_SERVER_1_2},
}
EXTEND_SESSION_STRICT: dict[str, Any] = _closed(EXTEND_SESSION, ())
RETRIEVE_SESSIONS_STRICT: dict[str, Any] = _closed(RETRIEVE_SESSIONS, ())
RETRIEVE_PROFILES_STRICT: dict[str, Any] = _closed(RETRIEVE_PROFILES, ())


def problem(schema: dict[str, Any], value: Any) -> str | None:
    """None if `value` fits `schema`, else the first violation, as a CAMARA error message would say it."""
    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(schema).iter_errors(value))
    if error is None:
        return None
    where = ".".join(str(p) for p in error.absolute_path) or "body"
    return f"{where}: {error.message}"[:300]
