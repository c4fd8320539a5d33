"""The emulated NEF's AsSessionWithQoS routes (TS 29.122 V18.4.0, 3gpp-as-session-with-qos v1) over its
subscriptions (sim/network/nef.py): each change may change the cell's grants. Errors are ProblemDetails;
a PATCH is a JSON merge patch."""

from __future__ import annotations

from typing import Any

from aiohttp import web

from dynqos.sim.network.control_http import Changed, Reply, answer, body
from dynqos.sim.network.nef import API, Nef, problem

MERGE_PATCH = "application/merge-patch+json"


class NefRoutes:
    def __init__(self, nef: Nef, changed: Changed) -> None:
        self.nef = nef
        self.changed = changed

    def routes(self) -> list[web.RouteDef]:
        one = API + "/{scs}/subscriptions/{sid}"
        return [
            web.post(API + "/{scs}/subscriptions", self.create),
            web.get(API + "/{scs}/subscriptions", self.all),
            web.get(one, self.get),
            web.put(one, self.replace),
            web.patch(one, self.modify),
            web.delete(one, self.delete),
        ]

    def _known(self, request: web.Request) -> None:
        """A 403 for an SCS/AS this NEF does not serve ([cell] nef_scs_as_ids; empty: any)."""
        known = self.nef.cell.nef_scs_as_ids
        if known and request.match_info["scs"] not in known:
            self.nef.counters.rejected += 1
            why = f"SCS/AS {request.match_info['scs'][:64]!r} is not one this NEF serves"
            raise Reply(problem(403, "SCS_AS_NOT_AUTHORIZED", why))

    async def create(self, request: web.Request) -> web.Response:
        self._known(request)
        result, notes = self.nef.create(request.match_info["scs"], await _body(request, "application/json"))
        self.changed(notes)
        return answer(result)

    async def all(self, request: web.Request) -> web.Response:
        self._known(request)
        self.changed(self.nef.advance())
        query = request.query
        mac_addrs = query.getall("mac-addrs", [])
        return answer(self.nef.all(request.match_info["scs"], query.get("ip-addrs"), mac_addrs))

    async def get(self, request: web.Request) -> web.Response:
        self._known(request)
        self.changed(self.nef.advance())
        return answer(self.nef.get(request.match_info["scs"], request.match_info["sid"]))

    async def replace(self, request: web.Request) -> web.Response:
        self._known(request)
        sent = await _body(request, "application/json")
        self.changed(self.nef.advance())
        result = self.nef.replace(request.match_info["scs"], request.match_info["sid"], sent)
        self.changed([])  # the flows or the reference may have changed
        return answer(result)

    async def modify(self, request: web.Request) -> web.Response:
        self._known(request)
        changes = await _body(request, MERGE_PATCH)
        self.changed(self.nef.advance())
        result = self.nef.modify(request.match_info["scs"], request.match_info["sid"], changes)
        self.changed([])  # the flows or the reference may have changed
        return answer(result)

    async def delete(self, request: web.Request) -> web.Response:
        self._known(request)
        result = self.nef.delete(request.match_info["scs"], request.match_info["sid"])
        self.changed([])
        return answer(result)


async def _body(request: web.Request, content_type: str) -> Any:
    """The request's JSON, of the content type the call takes; a ProblemDetails 400 or 415 otherwise."""
    if request.content_type != content_type:
        why = f"this call takes {content_type}, not {request.content_type or 'no body'}"
        raise Reply(problem(415, "UNSUPPORTED_MEDIA_TYPE", why))
    return await body(request, lambda why: problem(400, "INVALID_MSG_FORMAT", why))
