"""The cell emulator's control port over HTTP (aiohttp, on the emulator's own asyncio loop): the
emulator's own routes, and in front of them the emulated operator's APIs, one module each:

    GET  /counters                          per-bearer and background counters, QoD sessions
    POST /events                            apply a timeline event now (the same table as [[cell.events]])
    GET  /radio/{uav}                       what the drone's modem would report ([cell.radio])
    /quality-on-demand/v1/..., /qos-profiles/v1/...      QoD and QoS Profiles (api_qod.py)
    /qos-booking/v0.1/...                   QoS Booking (api_booking.py)
    /predictive-connectivity-data/v0.1/...  Predictive Connectivity Data (api_connectivity.py)
    /3gpp-as-session-with-qos/v1/...        the 5G core's NEF, when [cell] nef = true (api_nef.py)
    POST /oauth2/token, DELETE /oauth2/tokens  tokens, when [cell] qod_auth = true (oauth.py)

Served on 127.0.0.1 only. Every CAMARA call is authorised and its x-correlator checked and echoed
(CAMARA Commonalities); notifications go out through the notifier (notify.py), in the background.
"""

from __future__ import annotations

import logging
import re
from typing import Any, Protocol

from aiohttp import web

from dynqos.common.config import CellConfig, CellEventConfig, build
from dynqos.common.errors import ConfigError
from dynqos.common.http_log import quiet_malformed_requests
from dynqos.sim.network.api_booking import BOOKING_PREFIX, BookingRoutes
from dynqos.sim.network.api_connectivity import CONNECTIVITY_PREFIX, ConnectivityRoutes
from dynqos.sim.network.api_nef import NefRoutes
from dynqos.sim.network.api_qod import PROFILES_PREFIX, QOD_PREFIX, QodRoutes
from dynqos.sim.network.control_http import MAX_BODY_BYTES, Handler, Reply, answer, body, loads
from dynqos.sim.network.nef import API as NEF_API
from dynqos.sim.network.nef import problem
from dynqos.sim.network.notify import Notifier
from dynqos.sim.network.oauth import TokenEndpoint
from dynqos.sim.network.operator import Notification, error
from dynqos.sim.network.operator_apis import OperatorApis
from dynqos.sim.network.radio_feed import RadioFeed

log = logging.getLogger(__name__)
REQUEST_LINE = 65_536  # bytes of a request line or header field the control API reads

CAMARA_PREFIXES = (QOD_PREFIX, PROFILES_PREFIX, CONNECTIVITY_PREFIX, BOOKING_PREFIX)
CORRELATOR = re.compile(r"[a-zA-Z0-9\-_:;./<>{}]{0,256}")  # XCorrelator in both APIs' documents


class Emulator(Protocol):
    """What the control API needs of the cell emulator (sim/network/cell.py)."""

    cell: CellConfig
    radio: RadioFeed | None  # [cell.radio]: what each drone's modem would report

    def counters(self) -> dict[str, Any]: ...
    def apply(self, event: CellEventConfig) -> str: ...
    def refresh_grants(self) -> None: ...


class Tap(Protocol):
    """Sees every exchange: method, path, request JSON, status, response JSON."""

    def __call__(self, method: str, path: str, sent: Any, status: int, got: Any, /) -> None: ...


class ControlApi:
    def __init__(
        self,
        emulator: Emulator,
        operator: OperatorApis | None,
        notifier: Notifier,
        client_id: str = "",
        secret: str = "",
        *,
        client_key: Any = None,
        api_headers: dict[str, str] | None = None,
        tap: Tap | None = None,
    ) -> None:
        """`operator`: the emulated operator's sessions and bookings ([cell] qod = true); the token
        endpoint takes `secret` or assertions signed by `client_key`, or `api_headers` instead."""
        self.emulator = emulator
        self.operator = operator
        self.notifier = notifier
        self.tap = tap
        devices = operator.qod.devices if operator is not None else {}
        self.auth = TokenEndpoint(
            emulator.cell.qod_token_ttl_s,
            client_id,
            secret,
            client_key=client_key,
            api_headers=api_headers,
            device_of_phone=lambda phone: next(
                (uav for uav, d in devices.items() if d.get("phoneNumber") == phone), ""
            ),
        )
        self.app = web.Application(client_max_size=MAX_BODY_BYTES, middlewares=[self._errors])
        routes = [
            web.get("/counters", self.counters),
            web.post("/events", self.events),
            web.get("/radio/{uav}", self.radio),
            *self.auth.routes(),
        ]
        if operator is not None:
            routes += QodRoutes(operator.qod, operator.advance, self._changed).routes()
            if operator.bookings is not None:
                routes += BookingRoutes(operator.bookings, self._changed).routes()
            if operator.nef is not None:
                routes += NefRoutes(operator.nef, self._changed).routes()
        self.connectivity = ConnectivityRoutes(emulator.radio.predictor) if emulator.radio else None
        if self.connectivity is not None:
            routes += self.connectivity.routes()
        self.app.add_routes(routes)
        self.runner: web.AppRunner | None = None
        self.port = 0

    async def start(self, port: int) -> int:
        quiet_malformed_requests()
        # A query naming many UEs (ip-addrs, mac-addrs) is longer than aiohttp's 8190-byte request line:
        # read up to 64 KiB so the API answers it (in its own error shape) rather than the HTTP parser.
        self.runner = web.AppRunner(
            self.app,
            access_log=None,
            handle_signals=False,
            max_line_size=REQUEST_LINE,
            max_field_size=REQUEST_LINE,
        )
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", port)
        await site.start()
        self.port = int(self.runner.addresses[0][1])  # the port bound (the configured one may be 0)
        if self.operator is not None and self.operator.nef is not None:
            self.operator.nef.root = f"http://127.0.0.1:{self.port}"  # its subscriptions' `self` links
        if self.connectivity is not None:
            self.connectivity.start()
        return self.port

    async def stop(self) -> None:
        if self.runner is not None:
            await self.runner.cleanup()
        if self.connectivity is not None:
            self.connectivity.close()

    def _changed(self, notes: list[Notification]) -> None:
        self.emulator.refresh_grants()
        self.notifier.send(notes)

    # ---- plumbing ---------------------------------------------------------------------------------------

    @web.middleware
    async def _errors(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        response = await self._answer(request, handler)
        if self.tap is not None:
            sent = await request.read()
            got = response.body if isinstance(response, web.Response) else None
            self.tap(
                request.method,
                request.path,
                loads(sent) if request.content_type == "application/json" else dict(await request.post()),
                response.status,
                loads(got) if isinstance(got, bytes) else None,
            )
        return response

    async def _answer(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """A CAMARA call is authorised and its x-correlator checked and echoed (CAMARA Commonalities)."""
        if not request.path.startswith(CAMARA_PREFIXES):
            return await self._handle(request, handler)
        correlator = request.headers.get("x-correlator")
        if correlator is not None and not CORRELATOR.fullmatch(correlator):
            return answer(
                error(400, "INVALID_ARGUMENT", "x-correlator does not match ^[a-zA-Z0-9-_:;./<>{}]{0,256}$")
            )
        response = await self._handle(request, handler)
        if correlator is not None:
            response.headers["x-correlator"] = correlator
        return response

    async def _handle(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        try:
            prefix = next((p for p in CAMARA_PREFIXES if request.path.startswith(p)), None)
            if prefix is not None:
                self._serves(prefix)
                if self.emulator.cell.qod_auth:
                    self.auth.authorise(request, prefix)
            return await handler(request)
        except Reply as reply:
            return answer(reply.answer)
        except web.HTTPException as exc:
            if request.path.startswith(NEF_API):
                response = answer(problem(exc.status, exc.reason.upper().replace(" ", "_"), exc.reason))
            elif request.path.startswith(CAMARA_PREFIXES):
                code = {404: "NOT_FOUND", 405: "METHOD_NOT_ALLOWED"}.get(exc.status, "INVALID_ARGUMENT")
                response = answer(error(exc.status, code, exc.reason))
            else:
                response = web.json_response(
                    {"error": f"no {request.method} {request.path}; use GET /counters or POST /events"},
                    status=exc.status,
                )
            if "Allow" in exc.headers:  # a 405 says which methods the resource takes (RFC 9110, 15.5.6)
                response.headers["Allow"] = exc.headers["Allow"]
            return response

    def _serves(self, prefix: str) -> None:
        """Reply 404, saying why, for an API this cell does not serve."""
        if prefix == CONNECTIVITY_PREFIX and self.connectivity is None:
            why = "this cell serves no Predictive Connectivity Data ([cell.radio] enabled = false)"
            raise Reply(error(404, "NOT_FOUND", why))
        if prefix != CONNECTIVITY_PREFIX and self.operator is None:
            raise Reply(error(404, "NOT_FOUND", "this cell serves no QoD API ([cell] qod = false)"))

    # ---- the emulator's own routes ---------------------------------------------------------------------

    async def counters(self, request: web.Request) -> web.Response:
        counters = self.emulator.counters()
        if self.operator is not None:
            counters["qod"] = {
                **vars(self.operator.counters),
                "notified": self.notifier.notified,
                "notify_failures": self.notifier.notify_failures,
                "tokens_issued": self.auth.tokens_issued,
                "tokens_refused": self.auth.tokens_refused,
                "sessions": self.operator.open_sessions(),
            }
            if self.operator.nef is not None:
                counters["nef"] = vars(self.operator.nef.counters)
        return web.json_response(counters)

    async def radio(self, request: web.Request) -> web.Response:
        """What a drone's modem would report: its RSRP and SINR where the cell last placed it
        ([cell.radio]); 404 with a reason while there is none. The onboard daemon's `cell` modem reads it."""
        uav = request.match_info["uav"]
        feed = self.emulator.radio
        if feed is None:
            return web.json_response(
                {"error": "this cell has no radio map ([cell.radio] enabled = false)"}, status=404
            )
        report = feed.report(uav)
        if report is None:
            return web.json_response({"error": f"no position heard for {uav!r} lately"}, status=404)
        return web.json_response(report)

    async def events(self, request: web.Request) -> web.Response:
        try:
            table = await body(request)
            if table is None:
                table = {}
            if not isinstance(table, dict):
                raise ConfigError("body", "must be a JSON object")
            table.setdefault("at_s", 0.0)
            event = build(CellEventConfig, table)
            text = self.emulator.apply(event)
        except Reply as reply:
            return web.json_response({"error": reply.answer.body["message"]}, status=400)
        except ConfigError as exc:
            return web.json_response({"error": str(exc)}, status=400)
        return web.json_response({"applied": text})
