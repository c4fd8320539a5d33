"""The QoS agent's notification sink: the operator POSTs a CloudEvent (QOS_STATUS_CHANGED) to the `sink`
URL the agent gave with each session, and the agent reads that session at once instead of at its next
poll. The event's body is not trusted for the session's state: it only says which session to read.

Nor is the event trusted to come from the operator: the agent gives each session a `sinkCredential`
(CAMARA's ACCESSTOKEN: a bearer token of its own, valid past the session's end), and the sink takes an
event only with that token, a CloudEvents `specversion` 1.0, the QoD status-changed `type`, and an `id`
it has not seen (a replay is answered 204 and ignored). Anything else is a 400 or a 401 and changes
nothing."""

from __future__ import annotations

import collections
import hmac
import json
import logging
import secrets
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any
from urllib.parse import urlsplit

from aiohttp import web

from dynqos.common.camara import EVENT_TYPE
from dynqos.common.http_log import quiet_malformed_requests

log = logging.getLogger(__name__)

MAX_BODY = 64 * 1024
SEEN_IDS = 4096  # event ids remembered against replays: far more than a session's lifetime of events
CREDENTIAL_MARGIN_S = 3600  # the token given with a session stays valid this long past its end


@dataclass
class SinkGuard:
    """The token the sink expects and the event ids it has taken. Pure: no I/O."""

    token: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    seen: collections.OrderedDict[str, None] = field(default_factory=collections.OrderedDict)
    counters: dict[str, int] = field(
        default_factory=lambda: {"taken": 0, "unauthenticated": 0, "malformed": 0, "replayed": 0}
    )

    def credential(self, session_s: float, now_unix: float) -> dict[str, Any]:
        """The create body's `sinkCredential`: this token, valid past the session's end."""
        expires = datetime.fromtimestamp(now_unix + session_s + CREDENTIAL_MARGIN_S, timezone.utc)
        return {
            "credentialType": "ACCESSTOKEN",
            "accessToken": self.token,
            "accessTokenExpiresUtc": expires.isoformat(timespec="seconds").replace("+00:00", "Z"),
            "accessTokenType": "bearer",
        }

    def check(self, authorization: str, body: bytes) -> tuple[int, str | None, str]:
        """(HTTP status to answer, the session to read or None, why) for one POST to the sink."""
        given = authorization.removeprefix("Bearer ").strip() if authorization.startswith("Bearer ") else ""
        if not given or not hmac.compare_digest(given.encode(), self.token.encode()):
            self.counters["unauthenticated"] += 1
            return 401, None, "no valid bearer token"
        try:
            event = json.loads(body)
            event_id, session_id = event["id"], event["data"]["sessionId"]
            kind, version = event["type"], event["specversion"]
        except (ValueError, KeyError, TypeError):
            self.counters["malformed"] += 1
            return 400, None, "not a CloudEvent with data.sessionId"
        if version != "1.0" or kind != EVENT_TYPE or not isinstance(event_id, str) or not event_id:
            self.counters["malformed"] += 1
            return 400, None, f"not a QoD status change (specversion {version!r}, type {kind!r})"
        if not isinstance(session_id, str):
            self.counters["malformed"] += 1
            return 400, None, "data.sessionId is not a string"
        if event_id in self.seen:
            self.counters["replayed"] += 1
            return 204, None, f"event {event_id} seen before"
        self.seen[event_id] = None
        while len(self.seen) > SEEN_IDS:
            self.seen.popitem(last=False)
        self.counters["taken"] += 1
        return 204, session_id, ""


async def serve_sink(
    sink_url: str, listen: str, notified: Callable[[str], None], guard: SinkGuard
) -> web.AppRunner:
    """Serve POSTs to `sink_url`'s path on `listen` (host:port) until the runner is cleaned up; each event
    `guard` takes has its `data.sessionId` passed to `notified`."""
    path = urlsplit(sink_url).path or "/"

    async def receive(request: web.Request) -> web.Response:
        status, session_id, why = guard.check(request.headers.get("Authorization", ""), await request.read())
        refused = guard.counters["unauthenticated"] + guard.counters["malformed"]
        if status >= 400 and (refused <= 10 or refused % 100 == 0):  # a flood cannot flood the log
            log.warning(
                "qos agent: refused a notification from %s (%d so far): %s", request.remote, refused, why
            )
        if session_id is not None:
            notified(session_id)
        return web.Response(status=status)

    runner = await serve_posts(path, listen, receive)
    log.info("qos agent: notifications on %s (%s)", listen, path)
    return runner


async def serve_posts(
    path: str, listen: str, receive: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.AppRunner:
    """POSTs to `path` (an aiohttp route, `{name}` segments allowed) served on `listen` (host:port) by
    `receive`, bodies up to MAX_BODY, until the runner is cleaned up."""
    quiet_malformed_requests()
    app = web.Application(client_max_size=MAX_BODY)
    app.router.add_post(path, receive)
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    host, _, port = listen.rpartition(":")
    await web.TCPSite(runner, host.strip("[]"), int(port)).start()
    return runner
