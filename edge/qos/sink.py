"""The QoS agent's notification sink: the operator POSTs a CloudEvent (QOS_STATUS_CHANGED) to the `sink`
URL the agent gave with each session, and the agent reads that session at once instead of at its next
poll. The event's body is not trusted for the session's state: it only says which session to read."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from urllib.parse import urlsplit

from aiohttp import web

log = logging.getLogger(__name__)

MAX_BODY = 64 * 1024


async def serve_sink(sink_url: str, listen: str, notified: Callable[[str], None]) -> web.AppRunner:
    """Serve POSTs to `sink_url`'s path on `listen` (host:port) until the runner is cleaned up; each
    event's `data.sessionId` goes to `notified`. A body that is not such an event is a 400."""
    path = urlsplit(sink_url).path or "/"

    async def receive(request: web.Request) -> web.Response:
        try:
            event = json.loads(await request.read())
            session_id = event["data"]["sessionId"]
        except (ValueError, KeyError, TypeError):
            return web.Response(status=400)
        if not isinstance(session_id, str):
            return web.Response(status=400)
        notified(session_id)
        return web.Response(status=204)

    app = web.Application(client_max_size=MAX_BODY)
    app.router.add_post(path, receive)
    runner = web.AppRunner(app, access_log=None, handle_signals=False)
    await runner.setup()
    host, _, port = listen.rpartition(":")
    await web.TCPSite(runner, host.strip("[]"), int(port)).start()
    log.info("qos agent: notifications on %s (%s)", listen, path)
    return runner
