"""CAMARA Quality-on-Demand (v1.1.0) and QoS Profiles (v1.1.0) routes of the emulated operator, over its
sessions (sim/network/operator.py): each change of a session may change the cell's grants."""

from __future__ import annotations

from collections.abc import Callable

from aiohttp import web

from dynqos.sim.network.control_http import Changed, answer, body, subject
from dynqos.sim.network.operator import Notification, Operator

QOD_PREFIX = "/quality-on-demand/v1"
PROFILES_PREFIX = "/qos-profiles/v1"


class QodRoutes:
    def __init__(
        self, operator: Operator, advance: Callable[[], list[Notification]], changed: Changed
    ) -> None:
        """`advance`: settle and expire what is due before a read (the operator's sessions and bookings)."""
        self.op = operator
        self.advance = advance
        self.changed = changed

    def routes(self) -> list[web.RouteDef]:
        return [
            web.post(QOD_PREFIX + "/sessions", self.create),
            web.get(QOD_PREFIX + "/sessions/{sid}", self.get),
            web.delete(QOD_PREFIX + "/sessions/{sid}", self.delete),
            web.post(QOD_PREFIX + "/sessions/{sid}/extend", self.extend),
            web.post(QOD_PREFIX + "/retrieve-sessions", self.retrieve),
            web.post(PROFILES_PREFIX + "/retrieve-qos-profiles", self.retrieve_profiles),
            web.get(PROFILES_PREFIX + "/qos-profiles/{name}", self.get_profile),
        ]

    async def create(self, request: web.Request) -> web.Response:
        result, notes = self.op.create(await body(request), subject=subject(request))
        self.changed(notes)
        return answer(result)

    async def get(self, request: web.Request) -> web.Response:
        self.changed(self.advance())
        return answer(self.op.get(request.match_info["sid"], subject(request)))

    async def delete(self, request: web.Request) -> web.Response:
        result, notes = self.op.delete(request.match_info["sid"], subject(request))
        self.changed(notes)
        return answer(result)

    async def extend(self, request: web.Request) -> web.Response:
        self.changed(self.advance())
        return answer(self.op.extend(request.match_info["sid"], await body(request), subject(request)))

    async def retrieve(self, request: web.Request) -> web.Response:
        self.changed(self.advance())
        return answer(self.op.retrieve(await body(request), subject=subject(request)))

    async def retrieve_profiles(self, request: web.Request) -> web.Response:
        return answer(self.op.profiles(await body(request)))

    async def get_profile(self, request: web.Request) -> web.Response:
        return answer(self.op.profile(request.match_info["name"]))
