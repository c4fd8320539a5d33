"""CAMARA QoS Booking (v0.1.0) routes of the emulated operator, over its bookings
(sim/network/booking.py): a booking made or deleted may change the cell's grants."""

from __future__ import annotations

from aiohttp import web

from dynqos.sim.network.booking import Bookings
from dynqos.sim.network.control_http import Changed, answer, body, subject

BOOKING_PREFIX = "/qos-booking/v0.1"


class BookingRoutes:
    def __init__(self, bookings: Bookings, changed: Changed) -> None:
        self.books = bookings
        self.changed = changed

    def routes(self) -> list[web.RouteDef]:
        return [
            web.post(BOOKING_PREFIX + "/device-qos-bookings", self.book),
            web.get(BOOKING_PREFIX + "/device-qos-bookings/{bid}", self.booking),
            web.delete(BOOKING_PREFIX + "/device-qos-bookings/{bid}", self.unbook),
            web.post(BOOKING_PREFIX + "/retrieve-device-qos-bookings", self.bookings_of),
        ]

    async def book(self, request: web.Request) -> web.Response:
        result, notes = self.books.create(await body(request), subject=subject(request))
        self.changed(notes)
        return answer(result)

    async def booking(self, request: web.Request) -> web.Response:
        self.changed(self.books.advance())  # what it says has started holds for the cell at once
        return answer(self.books.get(request.match_info["bid"], subject(request)))

    async def unbook(self, request: web.Request) -> web.Response:
        result, notes = self.books.delete(request.match_info["bid"], subject(request))
        self.changed(notes)
        return answer(result)

    async def bookings_of(self, request: web.Request) -> web.Response:
        self.changed(self.books.advance())
        return answer(self.books.retrieve(await body(request), subject=subject(request)))
