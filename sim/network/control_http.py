"""What every API module behind the control app (sim/network/control_api.py) answers with: an operator
`Answer` as JSON, a request's JSON body (a bad one a CAMARA 400), and `Reply`, raised to answer at once."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from typing import Any

from aiohttp import web

from dynqos.sim.network.operator import Answer, Notification, error

MAX_BODY_BYTES = 64 * 1024
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
Changed = Callable[[list[Notification]], None]  # the grants may have changed; tell these clients


class Reply(Exception):
    """Answer the request with this, at once."""

    def __init__(self, answer: Answer) -> None:
        self.answer = answer


def answer(answer: Answer) -> web.Response:
    headers = {} if answer.retry_after_s is None else {"Retry-After": str(answer.retry_after_s)}
    if answer.location:
        headers["Location"] = answer.location
    if answer.body is None:
        return web.Response(status=answer.status, headers=headers)
    return web.json_response(
        answer.body, status=answer.status, headers=headers, content_type=answer.content_type
    )


def camara_400(why: str) -> Answer:
    return error(400, "INVALID_ARGUMENT", why)


async def body(request: web.Request, bad: Callable[[str], Answer] = camara_400) -> Any:
    """The request's JSON body; a bad one is answered with `bad(why)` (a CAMARA 400 by default)."""
    if request.content_length is not None and request.content_length > MAX_BODY_BYTES:
        raise Reply(bad(f"body larger than {MAX_BODY_BYTES} bytes"))
    try:
        return json.loads(await request.read() or b"null")
    except ValueError as exc:
        raise Reply(bad(f"the body is not JSON ({exc})")) from None


def loads(data: bytes) -> Any:
    try:
        return json.loads(data) if data else None
    except ValueError:
        return data.decode(errors="replace")


def subject(request: web.Request) -> str:
    """The drone a three-legged token names ("" for a two-legged one), as the authorisation found it."""
    return str(request.get("subject", ""))
