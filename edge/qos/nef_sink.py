"""The QoS agent's sink for a NEF's notifications (UserPlaneNotificationData, TS 29.122 clause 5.14.2.1.3):
the only news of a subscription's state, since reading one returns what was asked, not what was granted.

AsSessionWithQoS defines no credential for the notifications (CAMARA's sinkCredential has no
counterpart), so the URL is the credential: the agent gives the NEF `notificationDestination` with a
path segment of 32 random bytes of its own, and the sink takes a POST only on that path. A POST
elsewhere under the sink's path is a 401; a body that is not a notification is a 400; a notification of
a subscription the agent does not hold changes nothing (counted as unknown). Over plain http on a
network others can read, the URL can be sniffed: use https (docs/qos.md)."""

from __future__ import annotations

import hmac
import json
import logging
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from aiohttp import web

from dynqos.edge.operator.nef import Report, reports
from dynqos.edge.qos.sink import serve_posts

log = logging.getLogger(__name__)


@dataclass
class NefSinkGuard:
    """The secret path segment and what the sink took or refused. Pure: no I/O."""

    token: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    counters: dict[str, int] = field(
        default_factory=lambda: {"taken": 0, "unauthenticated": 0, "malformed": 0, "unknown": 0}
    )

    def destination(self, base: str) -> str:
        """The notificationDestination to give the NEF: the configured URL and this agent's segment."""
        return f"{base.rstrip('/')}/{self.token}"

    def check(self, token: str, body: bytes) -> tuple[int, list[Report], str]:
        """(HTTP status to answer, the events taken, why not) for one POST to the sink."""
        if not hmac.compare_digest(token.encode(), self.token.encode()):
            self.counters["unauthenticated"] += 1
            return 401, [], "not this agent's notification path"
        try:
            taken = reports(json.loads(body))
        except ValueError as exc:
            self.counters["malformed"] += 1
            return 400, [], str(exc)
        self.counters["taken"] += 1
        return 204, taken, ""


async def serve_nef_sink(
    base: str, listen: str, notified: Callable[[list[Report]], None], guard: NefSinkGuard
) -> web.AppRunner:
    """Serve POSTs to `base`'s path and a segment on `listen` (host:port) until the runner is cleaned up;
    each notification `guard` takes has its events passed to `notified`."""
    path = (urlsplit(base).path or "").rstrip("/")

    async def receive(request: web.Request) -> web.Response:
        status, taken, why = guard.check(request.match_info["token"], await request.read())
        refused = guard.counters["unauthenticated"] + guard.counters["malformed"]
        if status >= 400 and (refused <= 10 or refused % 100 == 0):  # a flood cannot flood the log
            log.warning(
                "qos agent: refused a NEF notification from %s (%d so far): %s", request.remote, refused, why
            )
        if taken:
            notified(taken)
        return web.Response(status=status)

    runner = await serve_posts(path + "/{token}", listen, receive)
    log.info("qos agent: NEF notifications on %s (%s/...)", listen, path)
    return runner
