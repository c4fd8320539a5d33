"""The edge's client of CAMARA QoS Booking (0.1.0): priority booked ahead for a drone, a time and an area.

Calls go through the operator client (edge/operator/client.py): the same token (the agent's scopes
include the booking API's), x-correlator, retries of 429 and 5xx within the call's time-out, errors that
carry the API's code. An answer without the API's shape is a 502 BAD_RESPONSE. Whoever books releases:
`release_all` deletes every booking this client made that has not ended, for a mission's end or an
agent's stop, so that nothing stays booked.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import Any

from dynqos.common.camara import rfc3339, unix_time
from dynqos.common.config import CamaraConfig
from dynqos.edge.operator.client import OperatorClient, OperatorError, beside

STATUSES = ("REQUESTED", "SCHEDULED", "AVAILABLE", "UNAVAILABLE")


@dataclass(frozen=True, slots=True)
class BookingInfo:
    booking_id: str
    status: str
    start_unix: float
    duration_s: int
    status_info: str = ""

    @classmethod
    def parse(cls, body: Any) -> BookingInfo:
        try:
            if body["status"] not in STATUSES:
                raise ValueError(f"status {body['status']!r}")
            uuid.UUID(str(body["bookingId"]))
            duration = body["duration"]
            if not isinstance(duration, int) or duration < 1:
                raise ValueError("duration is not a positive integer")
            return cls(
                str(body["bookingId"]),
                body["status"],
                unix_time(body["startTime"]),
                duration,
                str(body.get("statusInfo", "")),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise OperatorError(502, "BAD_RESPONSE", f"qos booking: not a BookingInfo ({exc})") from None


def booking_root(cfg: CamaraConfig) -> str:
    """`booking_root`, or beside the QoD API ({apiRoot}/qos-booking/v0.1)."""
    return beside(cfg, cfg.booking_root, "qos-booking/v0.1")


def circle(center: tuple[float, float], radius_m: float) -> dict[str, Any]:
    """A service area: a circle around (latitude, longitude)."""
    return {
        "areaType": "CIRCLE",
        "center": {"latitude": center[0], "longitude": center[1]},
        "radius": radius_m,
    }


class BookingApi:
    """QoS Booking over an open OperatorClient."""

    def __init__(self, operator: OperatorClient, made: dict[str, BookingInfo] | None = None) -> None:
        self.operator = operator
        self.root = booking_root(operator.cfg)
        # every booking made, by id, as last seen: this client's, or (`made`) one that an earlier
        # session's client made, shared, so that this one releases them
        self.made: dict[str, BookingInfo] = {} if made is None else made

    async def book(
        self,
        device: dict[str, Any],
        start_unix: float,
        duration_s: int,
        area: dict[str, Any],
        *,
        qos_profile: str,
        server: dict[str, Any] | None = None,
        server_ports: list[int] | None = None,
    ) -> BookingInfo:
        body: dict[str, Any] = {
            "device": device,
            "qosProfile": qos_profile,
            "startTime": rfc3339(start_unix),
            "duration": int(duration_s),
            "serviceArea": area,
        }
        if server is not None:
            body["applicationServer"] = server
        if server_ports:
            body["applicationServerPorts"] = {"ports": list(server_ports)}
        info = BookingInfo.parse(await self._call("POST", "/device-qos-bookings", body, (201,)))
        self.made[info.booking_id] = info
        return info

    async def get(self, booking_id: str) -> BookingInfo:
        info = BookingInfo.parse(await self._call("GET", f"/device-qos-bookings/{booking_id}", None, (200,)))
        self.made[booking_id] = info
        return info

    async def delete(self, booking_id: str) -> None:
        try:
            await self._call("DELETE", f"/device-qos-bookings/{booking_id}", None, (204,))
        except OperatorError as exc:
            if exc.status != 404:  # already gone: released all the same
                raise
        self.made.pop(booking_id, None)

    async def retrieve(self, device: dict[str, Any]) -> list[BookingInfo]:
        body = await self._call("POST", "/retrieve-device-qos-bookings", {"device": device}, (200,))
        if not isinstance(body, list):
            raise OperatorError(502, "BAD_RESPONSE", "retrieve-device-qos-bookings did not answer an array")
        return [BookingInfo.parse(item) for item in body]

    async def release_all(self) -> list[str]:
        """Delete every booking this client made that has not ended; the ids it could not delete."""
        failed = []
        for booking_id, info in list(self.made.items()):
            if info.status == "UNAVAILABLE":
                self.made.pop(booking_id)
                continue
            try:
                await self.delete(booking_id)
            except OperatorError:
                failed.append(booking_id)
        return failed

    async def _call(
        self, method: str, path: str, body: dict[str, Any] | None, expect: tuple[int, ...]
    ) -> Any:
        return await self.operator.request(method, path, body, expect=expect, root=self.root)
