"""The cell emulator's control port over HTTP (aiohttp, on the emulator's own asyncio loop).

    GET  /counters                          per-bearer and background counters, QoD sessions
    POST /events                            apply a timeline event now (the same table as [[cell.events]])
    /quality-on-demand/v1/...               the emulated operator's CAMARA QoD API (sim/network/operator.py)
    /qos-profiles/v1/...                    its QoS Profiles API: retrieve-qos-profiles, qos-profiles/{name}
    POST /oauth2/token                      client-credentials tokens, when [cell] qod_auth = true
    DELETE /oauth2/tokens                   revoke every token (an operator rotating credentials)

Served on 127.0.0.1 only. Notifications to a session's sink are posted from here, in the background,
bounded in number and time: a slow sink cannot stall the TTI loop.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import re
import secrets
import time
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from aiohttp import ClientSession, ClientTimeout, web

from dynqos.common.camara import JWT_BEARER, JWT_BEARER_GRANT, SCOPES, scope_for, signing_algorithm
from dynqos.common.config import CellConfig, CellEventConfig, build
from dynqos.common.errors import ConfigError
from dynqos.sim.network.booking import Bookings
from dynqos.sim.network.operator import Answer, Notification, Operator, error
from dynqos.sim.network.operator_schema import problem
from dynqos.sim.network.prediction import Refused
from dynqos.sim.network.prediction_process import PredictionProcess
from dynqos.sim.network.prediction_schema import RETRIEVE_CONNECTIVITY_STRICT
from dynqos.sim.network.radio_feed import RadioFeed

log = logging.getLogger(__name__)

QOD_PREFIX = "/quality-on-demand/v1"
PROFILES_PREFIX = "/qos-profiles/v1"
CONNECTIVITY_PREFIX = "/predictive-connectivity-data/v0.1"
BOOKING_PREFIX = "/qos-booking/v0.1"
CAMARA_PREFIXES = (QOD_PREFIX, PROFILES_PREFIX, CONNECTIVITY_PREFIX, BOOKING_PREFIX)
MAX_ASSERTION_LIFETIME_S = 600  # a client assertion valid longer than this is refused
SEEN_ASSERTIONS = 4096  # jti values remembered against replays
CORRELATOR = re.compile(r"[a-zA-Z0-9\-_:;./<>{}]{0,256}")  # XCorrelator in both APIs' documents
MAX_BODY_BYTES = 64 * 1024
MAX_PENDING_NOTIFICATIONS = 64
NOTIFY_TIMEOUT_S = 2.0


class Emulator(Protocol):
    """What the control API needs of the cell emulator (sim/network/cell.py)."""

    cell: CellConfig
    radio: RadioFeed | None  # [cell.radio]: what each drone's modem would report

    def counters(self) -> dict[str, Any]: ...
    def apply(self, event: CellEventConfig) -> str: ...
    def refresh_grants(self) -> None: ...


Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
Tap = Callable[[str, str, Any, int, Any], None]  # method, path, request JSON, status, response JSON


def _json(answer: Answer) -> web.Response:
    headers = {} if answer.retry_after_s is None else {"Retry-After": str(answer.retry_after_s)}
    if answer.body is None:
        return web.Response(status=answer.status, headers=headers)
    return web.json_response(answer.body, status=answer.status, headers=headers)


async def _body(request: web.Request) -> Any:
    """The request's JSON body; a bad one is a CAMARA 400."""
    if request.content_length is not None and request.content_length > MAX_BODY_BYTES:
        raise _Reply(error(400, "INVALID_ARGUMENT", f"body larger than {MAX_BODY_BYTES} bytes"))
    try:
        return json.loads(await request.read() or b"null")
    except ValueError as exc:
        raise _Reply(error(400, "INVALID_ARGUMENT", f"the body is not JSON ({exc})")) from None


def _loads(data: bytes) -> Any:
    try:
        return json.loads(data) if data else None
    except ValueError:
        return data.decode(errors="replace")


class _Reply(Exception):
    def __init__(self, answer: Answer) -> None:
        self.answer = answer


class ControlApi:
    def __init__(
        self,
        emulator: Emulator,
        operator: Operator | None,
        client_id: str = "",
        secret: str = "",
        *,
        client_key: Any = None,
        api_headers: dict[str, str] | None = None,
        tap: Tap | None = None,
    ) -> None:
        """`secret`: the client secret its token endpoint takes; `client_key`: the client's registered
        public key, for private_key_jwt client assertions (either or both)."""
        self.emulator = emulator
        self.tap = tap
        self.operator = operator
        self.client_id = client_id
        self.secret = secret
        self.client_key = client_key
        self.api_headers = dict(api_headers or {})  # with these on a call, no token is needed
        # token -> expiry (monotonic), scopes, the drone a three-legged token names ("": two-legged)
        self.tokens: dict[str, tuple[float, frozenset[str], str]] = {}
        self.assertions: collections.OrderedDict[str, None] = collections.OrderedDict()  # jti seen
        self.pending: set[asyncio.Task[None]] = set()
        self.notified = 0
        self.notify_failures = 0
        self.tokens_issued = 0
        self.tokens_refused = 0  # a client that keeps asking with refused credentials shows here
        self.http: ClientSession | None = None
        self.app = web.Application(client_max_size=MAX_BODY_BYTES, middlewares=[self._errors])
        r = self.app.router
        r.add_get("/counters", self.counters)
        r.add_post("/events", self.events)
        r.add_get("/radio/{uav}", self.radio)
        r.add_post(QOD_PREFIX + "/sessions", self.create)
        r.add_get(QOD_PREFIX + "/sessions/{sid}", self.get)
        r.add_delete(QOD_PREFIX + "/sessions/{sid}", self.delete)
        r.add_post(QOD_PREFIX + "/sessions/{sid}/extend", self.extend)
        r.add_post(QOD_PREFIX + "/retrieve-sessions", self.retrieve)
        r.add_post(PROFILES_PREFIX + "/retrieve-qos-profiles", self.retrieve_profiles)
        r.add_get(PROFILES_PREFIX + "/qos-profiles/{name}", self.get_profile)
        r.add_post(CONNECTIVITY_PREFIX + "/retrieve", self.connectivity)
        r.add_post(BOOKING_PREFIX + "/device-qos-bookings", self.book)
        r.add_get(BOOKING_PREFIX + "/device-qos-bookings/{bid}", self.booking)
        r.add_delete(BOOKING_PREFIX + "/device-qos-bookings/{bid}", self.unbook)
        r.add_post(BOOKING_PREFIX + "/retrieve-device-qos-bookings", self.bookings_of)
        r.add_post("/oauth2/token", self.token)
        r.add_delete("/oauth2/tokens", self.revoke)
        self.runner: web.AppRunner | None = None
        self.port = 0
        self.predictions = PredictionProcess()

    async def start(self, port: int) -> int:
        self.http = ClientSession(timeout=ClientTimeout(total=NOTIFY_TIMEOUT_S))
        self.runner = web.AppRunner(self.app, access_log=None, handle_signals=False)
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", port)
        await site.start()
        self.port = int(self.runner.addresses[0][1])  # the port bound (the configured one may be 0)
        if self.emulator.radio is not None:
            self.predictions.start()  # before anyone asks: spawning it takes a second or so
        return self.port

    async def stop(self) -> None:
        for task in list(self.pending):
            task.cancel()
        if self.runner is not None:
            await self.runner.cleanup()
        if self.http is not None:
            await self.http.close()
        self.predictions.close()

    # ---- plumbing ---------------------------------------------------------------------------------------

    @web.middleware
    async def _errors(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        response = await self._answer(request, handler)
        if self.tap is not None:
            sent = await request.read()
            body = response.body if isinstance(response, web.Response) else None
            self.tap(
                request.method,
                request.path,
                _loads(sent) if request.content_type == "application/json" else dict(await request.post()),
                response.status,
                _loads(body) if isinstance(body, bytes) else None,
            )
        return response

    async def _answer(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """A CAMARA call is authorised and its x-correlator checked and echoed (CAMARA Commonalities)."""
        if not request.path.startswith(CAMARA_PREFIXES):
            return await self._handle(request, handler)
        correlator = request.headers.get("x-correlator")
        if correlator is not None and not CORRELATOR.fullmatch(correlator):
            return _json(
                error(400, "INVALID_ARGUMENT", "x-correlator does not match ^[a-zA-Z0-9-_:;./<>{}]{0,256}$")
            )
        response = await self._handle(request, handler)
        if correlator is not None:
            response.headers["x-correlator"] = correlator
        return response

    async def _handle(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        try:
            if request.path.startswith((QOD_PREFIX, PROFILES_PREFIX, BOOKING_PREFIX)):
                if self.operator is None:
                    return _json(error(404, "NOT_FOUND", "this cell serves no QoD API ([cell] qod = false)"))
                self._authorise(request)
            elif request.path.startswith(CONNECTIVITY_PREFIX):
                if self.emulator.radio is None:
                    return _json(
                        error(
                            404,
                            "NOT_FOUND",
                            "this cell serves no Predictive Connectivity Data ([cell.radio] enabled = false)",
                        )
                    )
                self._authorise(request)
            return await handler(request)
        except _Reply as reply:
            return _json(reply.answer)
        except web.HTTPException as exc:
            if request.path.startswith(CAMARA_PREFIXES):
                code = {404: "NOT_FOUND", 405: "METHOD_NOT_ALLOWED"}.get(exc.status, "INVALID_ARGUMENT")
                answer = _json(error(exc.status, code, exc.reason))
            else:
                answer = web.json_response(
                    {"error": f"no {request.method} {request.path}; use GET /counters or POST /events"},
                    status=exc.status,
                )
            if "Allow" in exc.headers:  # a 405 says which methods the resource takes (RFC 9110, 15.5.6)
                answer.headers["Allow"] = exc.headers["Allow"]
            return answer

    def _authorise(self, request: web.Request) -> None:
        if not self.emulator.cell.qod_auth:
            return
        if self.api_headers:  # an aggregator's fixed API-key headers instead of OAuth2
            if all(
                secrets.compare_digest(request.headers.get(k, ""), v) for k, v in self.api_headers.items()
            ):
                return
            raise _Reply(
                error(401, "UNAUTHENTICATED", "request not authenticated: the API key is missing or wrong")
            )
        header = request.headers.get("Authorization", "")
        token = header.removeprefix("Bearer ").strip() if header.startswith("Bearer ") else ""
        expiry, scopes, subject = self.tokens.get(token, (0.0, frozenset(), ""))
        if time.monotonic() >= expiry:
            self.tokens.pop(token, None)
            raise _Reply(
                error(401, "UNAUTHENTICATED", "request not authenticated: a valid token is required")
            )
        prefix = next(p for p in CAMARA_PREFIXES if request.path.startswith(p))
        needed = scope_for(request.method, request.path.removeprefix(prefix))
        if needed and needed not in scopes:
            raise _Reply(error(403, "PERMISSION_DENIED", f"the token lacks the scope {needed}"))
        request["subject"] = subject

    def send(self, notes: list[Notification]) -> None:
        """Post each notification to its sink in the background (bounded; the oldest work is not waited)."""
        for note in notes:
            if len(self.pending) >= MAX_PENDING_NOTIFICATIONS:
                self.notify_failures += 1
                log.warning("qod: too many notifications pending; dropping one for %s", note.sink)
                continue
            task = asyncio.get_running_loop().create_task(self._post(note))
            self.pending.add(task)
            task.add_done_callback(self.pending.discard)

    async def _post(self, note: Notification) -> None:
        assert self.http is not None
        headers = {"Content-Type": "application/cloudevents+json"}
        credential = note.credential or {}
        if credential.get("credentialType") == "ACCESSTOKEN" and credential.get("accessToken"):
            headers["Authorization"] = f"Bearer {credential['accessToken']}"
        try:
            async with self.http.post(note.sink, data=json.dumps(note.event), headers=headers) as response:
                ok = response.status in (200, 202, 204)
        except Exception as exc:  # any failure of a sink (refused, timed out, bad TLS) is the sink's
            ok = False
            log.warning("qod: notification to %s failed (%s)", note.sink, type(exc).__name__)
        self.notified += ok
        self.notify_failures += not ok

    def _changed(self, notes: list[Notification]) -> None:
        self.emulator.refresh_grants()
        self.send(notes)

    # ---- the emulator's own routes ---------------------------------------------------------------------

    async def counters(self, request: web.Request) -> web.Response:
        counters = self.emulator.counters()
        if self.operator is not None:
            counters["qod"] = {
                **vars(self.operator.counters),
                "notified": self.notified,
                "notify_failures": self.notify_failures,
                "tokens_issued": self.tokens_issued,
                "tokens_refused": self.tokens_refused,
                "sessions": self.operator.open_sessions(),
            }
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

    async def connectivity(self, request: web.Request) -> web.Response:
        """Predictive Connectivity Data 0.1.0's retrieve (sim/network/prediction.py)."""
        assert self.emulator.radio is not None  # _handle answered 404 otherwise
        body = await _body(request)
        wrong = problem(RETRIEVE_CONNECTIVITY_STRICT, body)
        if wrong is not None:
            return _json(error(400, "INVALID_ARGUMENT", wrong))
        try:
            text = await self.predictions.answer(self.emulator.radio.predictor, body, time.time())
        except Refused as refused:
            return _json(error(refused.status, refused.code, refused.message))
        return web.Response(body=text, content_type="application/json")

    # ---- QoS Booking 0.1.0 (sim/network/booking.py) ---------------------------------------------------

    @property
    def books(self) -> Bookings:
        assert self.operator is not None
        assert self.operator.bookings is not None
        return self.operator.bookings

    async def book(self, request: web.Request) -> web.Response:
        answer, notes = self.books.create(await _body(request), subject=request.get("subject", ""))
        self._changed(notes)
        return _json(answer)

    async def booking(self, request: web.Request) -> web.Response:
        return _json(self.books.get(request.match_info["bid"], request.get("subject", "")))

    async def unbook(self, request: web.Request) -> web.Response:
        answer, notes = self.books.delete(request.match_info["bid"], request.get("subject", ""))
        self._changed(notes)
        return _json(answer)

    async def bookings_of(self, request: web.Request) -> web.Response:
        return _json(self.books.retrieve(await _body(request), subject=request.get("subject", "")))

    async def events(self, request: web.Request) -> web.Response:
        try:
            table = await _body(request)
            if table is None:
                table = {}
            if not isinstance(table, dict):
                raise ConfigError("body", "must be a JSON object")
            table.setdefault("at_s", 0.0)
            event = build(CellEventConfig, table)
            text = self.emulator.apply(event)
        except _Reply as reply:
            return web.json_response({"error": reply.answer.body["message"]}, status=400)
        except ConfigError as exc:
            return web.json_response({"error": str(exc)}, status=400)
        return web.json_response({"applied": text})

    # ---- the QoD API ---------------------------------------------------------------------------------------

    @property
    def op(self) -> Operator:
        assert self.operator is not None
        return self.operator

    async def create(self, request: web.Request) -> web.Response:
        answer, notes = self.op.create(await _body(request), subject=request.get("subject", ""))
        self._changed(notes)
        return _json(answer)

    async def get(self, request: web.Request) -> web.Response:
        self._changed(self.op.advance())
        return _json(self.op.get(request.match_info["sid"], request.get("subject", "")))

    async def delete(self, request: web.Request) -> web.Response:
        answer, notes = self.op.delete(request.match_info["sid"], request.get("subject", ""))
        self._changed(notes)
        return _json(answer)

    async def extend(self, request: web.Request) -> web.Response:
        self._changed(self.op.advance())
        return _json(
            self.op.extend(request.match_info["sid"], await _body(request), request.get("subject", ""))
        )

    async def retrieve(self, request: web.Request) -> web.Response:
        self._changed(self.op.advance())
        return _json(self.op.retrieve(await _body(request), subject=request.get("subject", "")))

    async def retrieve_profiles(self, request: web.Request) -> web.Response:
        return _json(self.op.profiles(await _body(request)))

    async def get_profile(self, request: web.Request) -> web.Response:
        return _json(self.op.profile(request.match_info["name"]))

    async def token(self, request: web.Request) -> web.Response:
        answer = await self._token(request)
        if answer.status == 200:
            self.tokens_issued += 1
        else:
            self.tokens_refused += 1
        return answer

    async def _token(self, request: web.Request) -> web.Response:
        """OAuth2: client credentials, the client authenticated by its secret or a client assertion
        (private_key_jwt); or the JWT-bearer grant for one device (three-legged: the assertion's `sub` is
        the device's `tel:` login hint). The token carries the scopes asked (all when none is asked)."""
        form = await request.post()
        grant = form.get("grant_type")
        subject = ""
        if grant == JWT_BEARER_GRANT:
            claims = self._verified(str(form.get("assertion", "")))
            subject = self._device_of_hint(str(claims.get("sub", ""))) if claims else ""
            if not subject:
                return web.json_response({"error": "invalid_grant"}, status=400)
        elif grant != "client_credentials":
            return web.json_response({"error": "unsupported_grant_type"}, status=400)
        elif not self._client_authenticated(form):
            return web.json_response({"error": "invalid_client"}, status=401)
        asked = frozenset(str(form.get("scope", "")).split()) or frozenset(SCOPES.values())
        if not asked <= frozenset(SCOPES.values()):
            unknown = " ".join(sorted(asked - frozenset(SCOPES.values())))
            return web.json_response({"error": "invalid_scope", "error_description": unknown}, status=400)
        token = secrets.token_urlsafe(24)
        ttl = self.emulator.cell.qod_token_ttl_s
        now = time.monotonic()
        self.tokens = {t: v for t, v in self.tokens.items() if v[0] > now}  # bounded: live ones only
        self.tokens[token] = (now + ttl, asked, subject)
        return web.json_response(
            {
                "access_token": token,
                "token_type": "Bearer",
                "expires_in": ttl,
                "scope": " ".join(sorted(asked)),
            }
        )

    def _client_authenticated(self, form: Any) -> bool:
        if not self.client_id or form.get("client_id", self.client_id) != self.client_id:
            return False
        if "client_assertion" in form:
            if form.get("client_assertion_type") != JWT_BEARER:
                return False
            claims = self._verified(str(form["client_assertion"]))
            return claims is not None and claims["sub"] == self.client_id
        return bool(self.secret) and secrets.compare_digest(str(form.get("client_secret", "")), self.secret)

    def _device_of_hint(self, hint: str) -> str:
        """The drone whose phone number a `tel:` login hint names ("" when none)."""
        phone = hint.removeprefix("tel:") if hint.startswith("tel:") else ""
        operator = self.operator
        if not phone or operator is None:
            return ""
        return next((uav for uav, d in operator.devices.items() if d.get("phoneNumber") == phone), "")

    def _verified(self, assertion: str) -> dict[str, Any] | None:
        """RFC 7523's checks of an assertion: signed by the registered key, issued by the client, for this
        token endpoint (any host, its path), at most MAX_ASSERTION_LIFETIME_S long, its `jti` never used
        before. Its claims, or None."""
        if self.client_key is None:
            return None
        import jwt

        try:
            claims: dict[str, Any] = jwt.decode(
                assertion,
                self.client_key,
                algorithms=[signing_algorithm(self.client_key)],
                issuer=self.client_id,
                options={"require": ["exp", "iat", "jti", "aud", "sub"], "verify_aud": False},
            )
        except jwt.PyJWTError as exc:
            log.info("qod: assertion refused: %s", exc)
            return None
        audience = claims["aud"] if isinstance(claims["aud"], list) else [claims["aud"]]
        if not any(str(a).endswith("/oauth2/token") for a in audience):
            return None
        if claims["exp"] - claims["iat"] > MAX_ASSERTION_LIFETIME_S or claims["jti"] in self.assertions:
            return None
        self.assertions[str(claims["jti"])] = None
        while len(self.assertions) > SEEN_ASSERTIONS:
            self.assertions.popitem(last=False)
        return claims

    async def revoke(self, request: web.Request) -> web.Response:
        count = len(self.tokens)
        self.tokens.clear()
        return web.json_response({"revoked": count})
