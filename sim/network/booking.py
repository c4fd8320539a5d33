"""The emulated operator's CAMARA QoS Booking (0.1.0): priority booked ahead for a time and an area.

A planner that knows when a drone will inspect something risky books the priority flow for that window
and place, instead of asking for a QoD session when the latency is already high. A booking names its
device, QoS profile, start, duration and service area (a circle or a polygon; an area name is not
managed here); it is SCHEDULED until its start, AVAILABLE until its end (DURATION_EXPIRED), and
UNAVAILABLE when deleted (DELETE_REQUESTED) or refused. While AVAILABLE, the drone's priority bearer
has its weight, as with a QoD session, but only while the cell places the drone inside the booked area
(with the radio map on; without it, anywhere). Admission: at most `[cell] booking_max_concurrent`
bookings may overlap in time (a booking beyond that is created UNAVAILABLE, as the API allows); a
booking that overlaps another of the same device's flows is a 409. Unavailable bookings are kept for
360 s so that a client that polls sees how they ended, as the API says, then forgotten.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dynqos.common.camara import ports_named, rfc3339, unix_time
from dynqos.common.geo import Geo
from dynqos.sim.network.booking_schema import CREATE_BOOKING_STRICT, RETRIEVE_BOOKINGS_STRICT
from dynqos.sim.network.operator import Answer, Notification, Operator, error
from dynqos.sim.network.operator_schema import problem
from dynqos.sim.network.prediction import inside, polygon_area, simple_polygon

EVENT_TYPE = "org.camaraproject.qos-booking.v0.status-changed"
KEEP_UNAVAILABLE_S = 360.0  # the API: an UNAVAILABLE booking is deleted at earliest this long after
MAX_BOOKINGS = 1000  # a client that never deletes meets 429, not a memory leak
Where = Callable[[str], "tuple[float, float] | None"]  # drone -> its (x, y) now, or None when unknown


@dataclass
class Booking:
    booking_id: str
    uav: str
    body: dict[str, Any]
    start: float  # Unix seconds
    duration_s: int
    status: str = "SCHEDULED"
    status_info: str = ""
    started: float | None = None
    ended: float | None = None

    @property
    def end(self) -> float:
        return self.start + self.duration_s

    def ports(self) -> set[int]:
        return ports_named(self.body.get("applicationServerPorts"))


class Bookings:
    """Bookings of one emulated operator; `wall` is its clock (Unix seconds), `where` the cell's view of
    each drone's position, `covered` whether a local (x, y) is inside the operator's coverage."""

    def __init__(
        self,
        operator: Operator,
        wall: Callable[[], float],
        geo: Geo,
        where: Where,
        covered: Callable[[float, float], bool],
        max_concurrent: int = -1,
    ) -> None:
        self.operator = operator
        self.wall = wall
        self.geo = geo
        self.where = where
        self.covered = covered
        self.max_concurrent = max_concurrent
        self.bookings: dict[str, Booking] = {}
        self.created = self.refused = self.deleted = self.expired = 0

    # ---- the API ----------------------------------------------------------------------------------------

    def create(self, body: Any, subject: str = "") -> tuple[Answer, list[Notification]]:
        bad = problem(CREATE_BOOKING_STRICT, body)
        if bad is not None:
            return error(400, "INVALID_ARGUMENT", bad), []
        uav, refused = self.operator.identify(body, subject)
        if refused is not None:
            return refused, []
        op = self.operator
        if body["qosProfile"] not in op.offered or body["qosProfile"] in op.inactive:
            return error(
                422, "SERVICE_NOT_APPLICABLE", f"profile {body['qosProfile']} is not offered here"
            ), []
        area = body["serviceArea"]
        if area["areaType"] == "AREANAME":
            return error(
                422, "QOS_BOOKING.NOT_MANAGED_AREA_TYPE", "The requested area type is not managed"
            ), []
        shape = self._shape(area)
        if shape is None:
            return error(422, "QOS_BOOKING.INVALID_AREA", "The requested area is too small or not simple"), []
        if not any(self.covered(x, y) for x, y in shape[1]):
            return error(422, "QOS_BOOKING.AREA_NOT_COVERED", "Unable to cover the requested area"), []
        now = self.wall()
        start = unix_time(body["startTime"])
        if start < now - 1.0:
            return error(400, "OUT_OF_RANGE", "startTime is in the past"), []
        self.advance()
        duration = min(body["duration"], op.max_duration_s(body["qosProfile"]))
        ports = ports_named(body.get("applicationServerPorts"))
        for other in self.bookings.values():
            overlaps = other.start < start + duration and start < other.end
            if (
                other.uav == uav
                and other.status != "UNAVAILABLE"
                and overlaps
                and (not ports or not other.ports() or ports & other.ports())
            ):
                return error(409, "CONFLICT", f"booking {other.booking_id} for this device overlaps it"), []
        if len(self.bookings) >= MAX_BOOKINGS:
            return error(429, "TOO_MANY_REQUESTS", "too many bookings; delete some"), []
        booking = Booking(str(uuid.uuid4()), uav, body, start, duration)
        self.bookings[booking.booking_id] = booking
        self.created += 1
        busy = sum(
            1
            for b in self.bookings.values()
            if b is not booking
            and b.status != "UNAVAILABLE"
            and b.start < booking.end
            and booking.start < b.end
        )
        if 0 <= self.max_concurrent <= busy:
            booking.status = "UNAVAILABLE"  # refused synchronously: 201 with UNAVAILABLE (the API)
            booking.ended = now
            self.refused += 1
            return Answer(201, self.info(booking)), self._notify(booking)
        notes = self._notify(booking) + self.advance()
        return Answer(201, self.info(booking)), notes

    def get(self, booking_id: str, subject: str = "") -> Answer:
        self.advance()
        booking = self._booking(booking_id, subject)
        return (
            error(404, "NOT_FOUND", "the booking does not exist")
            if booking is None
            else Answer(200, self.info(booking))
        )

    def delete(self, booking_id: str, subject: str = "") -> tuple[Answer, list[Notification]]:
        booking = self._booking(booking_id, subject)
        if booking is None:
            return error(404, "NOT_FOUND", "the booking does not exist"), []
        del self.bookings[booking_id]
        self.deleted += 1
        notes = []
        if booking.status in ("SCHEDULED", "AVAILABLE"):
            notes = self._end(booking, "DELETE_REQUESTED")
        return Answer(204), notes

    def retrieve(self, body: Any, subject: str = "") -> Answer:
        bad = problem(RETRIEVE_BOOKINGS_STRICT, body)
        if bad is not None:
            return error(400, "INVALID_ARGUMENT", bad)
        uav, refused = self.operator.identify(body, subject)
        if refused is not None:
            return refused
        self.advance()
        return Answer(200, [self.info(b) for b in self.bookings.values() if b.uav == uav])

    # ---- time and grants --------------------------------------------------------------------------------

    def advance(self) -> list[Notification]:
        """Start and end what is due now; forget what ended long ago."""
        now = self.wall()
        notes: list[Notification] = []
        for booking in list(self.bookings.values()):
            if booking.status == "SCHEDULED" and booking.start <= now:
                booking.status, booking.started = "AVAILABLE", max(booking.start, now - 1.0)
                notes += self._notify(booking)
            if booking.status == "AVAILABLE" and booking.end <= now:
                self.expired += 1
                notes += self._end(booking, "DURATION_EXPIRED")
            if booking.status == "UNAVAILABLE" and (booking.ended or now) + KEEP_UNAVAILABLE_S <= now:
                del self.bookings[booking.booking_id]
        return notes

    def granted(self, uav: str, port: int) -> bool:
        """An AVAILABLE booking of the drone covers this flow's port, and the drone is in its area."""
        for booking in self.bookings.values():
            if booking.uav != uav or booking.status != "AVAILABLE":
                continue
            if booking.ports() and port not in booking.ports():
                continue
            position = self.where(uav)
            if position is None or self._contains(booking.body["serviceArea"], position):
                return True
        return False

    def open_bookings(self) -> int:
        return sum(1 for b in self.bookings.values() if b.status in ("SCHEDULED", "AVAILABLE"))

    # ---- the rest ---------------------------------------------------------------------------------------

    def info(self, booking: Booking) -> dict[str, Any]:
        """The booking as a CAMARA BookingInfo."""
        body = booking.body
        out = {
            k: v for k, v in body.items() if k not in ("device", "sinkCredential", "startTime", "duration")
        }
        if "device" in body:
            out["device"] = dict([next(iter(body["device"].items()))])
        out |= {
            "bookingId": booking.booking_id,
            "status": booking.status,
            "startTime": rfc3339(booking.start),
            "duration": booking.duration_s,
        }
        if booking.started is not None:
            out["startedAt"] = rfc3339(booking.started)
            if booking.status == "UNAVAILABLE" and booking.ended is not None:
                out["duration"] = max(1, round(booking.ended - booking.started))
        if booking.status == "UNAVAILABLE" and booking.status_info:
            out["statusInfo"] = booking.status_info
        return out

    def _booking(self, booking_id: str, subject: str) -> Booking | None:
        booking = self.bookings.get(booking_id)
        return None if booking is None or (subject and booking.uav != subject) else booking

    def _end(self, booking: Booking, why: str) -> list[Notification]:
        booking.status, booking.status_info, booking.ended = "UNAVAILABLE", why, self.wall()
        return self._notify(booking)

    def _notify(self, booking: Booking) -> list[Notification]:
        data = {"bookingId": booking.booking_id, "status": booking.status}
        if booking.status_info:
            data["statusInfo"] = booking.status_info
        return self.operator.cloud_event(booking.body, EVENT_TYPE, data)

    def _shape(self, area: dict[str, Any]) -> tuple[str, list[tuple[float, float]]] | None:
        """The area in local metres: a circle's centre and a ring of points on it, or a polygon's corners;
        None when it is not a simple polygon of at least 1 m^2."""
        if area["areaType"] == "CIRCLE":
            cx, cy = self.geo.to_local(area["center"]["latitude"], area["center"]["longitude"])
            r = float(area["radius"])
            ring = [(cx + r * dx, cy + r * dy) for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1))]
            return "circle", [(cx, cy), *ring]
        corners = [self.geo.to_local(p["latitude"], p["longitude"]) for p in area["boundary"]]
        if not simple_polygon(corners) or polygon_area(corners) < 1.0:
            return None
        return "polygon", corners

    def _contains(self, area: dict[str, Any], position: tuple[float, float]) -> bool:
        shape = self._shape(area)
        if shape is None:
            return False
        kind, points = shape
        if kind == "circle":
            (cx, cy), r = points[0], float(area["radius"])
            return (position[0] - cx) ** 2 + (position[1] - cy) ** 2 <= r * r
        return inside(position, points)
