"""The agent's notification sink (edge/qos/sink.py) takes only what its operator sends: the bearer token
the agent gave with the session, a CloudEvent of the QoD status-changed type, an id not seen before.
The rules on their own, then over real HTTP on 127.0.0.1: forged, replayed and unauthenticated
notifications make the agent read nothing."""

from __future__ import annotations

import asyncio
import json
import uuid
from datetime import datetime
from typing import Any

import aiohttp
import pytest

from dynqos.common.camara import EVENT_TYPE
from dynqos.edge.qos.sink import SEEN_IDS, SinkGuard, serve_sink
from tests.conftest import free_tcp_port

pytestmark = pytest.mark.timeout(30)

SESSION = "3fa85f64-5717-4562-b3fc-2c963f66afa6"


def event(**changes: Any) -> bytes:
    data = {"sessionId": SESSION, "qosStatus": "UNAVAILABLE", "statusInfo": "NETWORK_TERMINATED"}
    body = {"id": str(uuid.uuid4()), "source": "https://operator.example/qod", "type": EVENT_TYPE,
            "specversion": "1.0", "time": "2026-11-24T01:00:00Z", "data": data}  # fmt: skip
    return json.dumps(body | changes).encode()


def test_the_credential_is_a_bearer_token_valid_past_the_session() -> None:
    guard = SinkGuard()
    credential = guard.credential(600, now_unix=1_800_000_000)
    assert credential["credentialType"] == "ACCESSTOKEN"
    assert credential["accessTokenType"] == "bearer"
    assert credential["accessToken"] == guard.token
    assert len(guard.token) >= 40  # 32 random bytes
    expires = datetime.fromisoformat(credential["accessTokenExpiresUtc"].replace("Z", "+00:00"))
    assert expires.timestamp() > 1_800_000_000 + 600
    assert SinkGuard().token != guard.token


def test_only_the_operator_s_events_are_taken_once_each() -> None:
    guard = SinkGuard()
    bearer = f"Bearer {guard.token}"
    assert guard.check("", event())[:2] == (401, None)
    assert guard.check("Bearer not-the-token", event())[:2] == (401, None)
    assert guard.check(bearer, b"not json")[:2] == (400, None)
    assert guard.check(bearer, event(type="org.example.other"))[:2] == (400, None)
    assert guard.check(bearer, event(specversion="0.3"))[:2] == (400, None)
    first = event()
    assert guard.check(bearer, first)[:2] == (204, SESSION)
    assert guard.check(bearer, first)[:2] == (204, None)  # a replay: answered, not acted on
    assert guard.counters == {"taken": 1, "unauthenticated": 2, "malformed": 3, "replayed": 1}
    for _ in range(SEEN_IDS + 10):
        guard.check(bearer, event())
    assert len(guard.seen) == SEEN_IDS  # bounded


def test_over_http_forged_replayed_and_unauthenticated_events_read_nothing() -> None:
    async def main() -> None:
        port = free_tcp_port()
        guard = SinkGuard()
        read: list[str] = []
        runner = await serve_sink(
            f"http://127.0.0.1:{port}/qod-events", f"127.0.0.1:{port}", read.append, guard
        )
        url = f"http://127.0.0.1:{port}/qod-events"
        try:
            async with aiohttp.ClientSession() as http:

                async def post(body: bytes, token: str | None) -> int:
                    headers = {"Content-Type": "application/cloudevents+json"}
                    if token is not None:
                        headers["Authorization"] = f"Bearer {token}"
                    async with http.post(url, data=body, headers=headers) as r:
                        return r.status

                assert await post(event(), None) == 401
                assert await post(event(), "guessed") == 401
                assert await post(event(type="com.attacker.fake"), guard.token) == 400
                assert read == []
                genuine = event()
                assert await post(genuine, guard.token) == 204
                assert await post(genuine, guard.token) == 204  # replayed
                assert read == [SESSION]
        finally:
            await runner.cleanup()

    asyncio.run(asyncio.wait_for(main(), 20))
