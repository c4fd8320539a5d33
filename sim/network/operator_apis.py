"""The emulated operator as the cell sees it: its QoD sessions (sim/network/operator.py) and, where the
QoS Booking API is served, its bookings (sim/network/booking.py). Either gives a drone's flow priority;
both settle and expire on the cell's clock. Built once, from its parts, before the cell that uses it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dynqos.sim.network.booking import Bookings
from dynqos.sim.network.cell_core import Effect
from dynqos.sim.network.nef import Delays, Nef
from dynqos.sim.network.operator import Notification, Operator, QodCounters


@dataclass(frozen=True)
class OperatorApis:
    qod: Operator
    bookings: Bookings | None = None
    nef: Nef | None = None  # [cell] nef: the 5G core's AsSessionWithQoS too

    @property
    def counters(self) -> QodCounters:
        return self.qod.counters

    def granted(self, uav: str, port: int) -> bool:
        """A QoD session, a booking or a NEF subscription gives this flow of the drone priority now."""
        return (
            self.qod.granted(uav, port)
            or (self.bookings is not None and self.bookings.granted(uav, port))
            or (self.nef is not None and self.nef.granted(uav, port))
        )

    def advance(self, delays: Delays | None = None) -> list[Notification]:
        """Settle and expire sessions and subscriptions, start and end bookings; called every few TTIs,
        with the cell's `delays` for the NEF's QoS monitoring reports."""
        notes = self.qod.advance() + (self.bookings.advance() if self.bookings is not None else [])
        return notes + (self.nef.advance(delays) if self.nef is not None else [])

    def apply(self, effect: Effect) -> list[Notification]:
        """What a timeline event asks of the operator (end sessions and subscriptions, change a profile)."""
        ended = self.nef.end(effect.end_qod) if self.nef is not None and effect.end_qod is not None else []
        return self.qod.apply(effect) + ended

    def open_sessions(self) -> list[dict[str, Any]]:
        return self.qod.open_sessions()
