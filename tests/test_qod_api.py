"""The CAMARA QoD client (edge/operator/client.py) against the emulated operator (sim/network/operator.py,
served by the cell's control API) over real HTTP on 127.0.0.1. Every request the client sends and every
answer the emulator returns is checked against the schemas written from the spec
(sim/network/operator_schema.py); what an operator may do that the emulator does not (throttle, fail,
hang) comes from a scripted server."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from aiohttp import web

from dynqos.common.config import CamaraConfig, CellConfig, ZenohConfig
from dynqos.edge.operator.client import OperatorError, retry_after_s
from dynqos.edge.qos.calls import settings_at_fault
from dynqos.edge.qos.profile_watch import ProfileWatch
from dynqos.sim.network import operator_schema as schema
from dynqos.sim.network.service import run_cell
from tests import camara_spec
from tests.operator_apis import qod_api

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

DEVICE = {"phoneNumber": "+46700000001"}
SECRET = "s3cret-for-tests"


def session_body(**changes: Any) -> dict[str, Any]:
    body = {
        "device": DEVICE,
        "applicationServer": {"ipv4Address": "127.0.0.1"},
        "applicationServerPorts": {"ports": [7448]},
        "qosProfile": "QOS_E",
        "duration": 60,
    }
    return body | changes


# Which schemas an exchange must fit: (method, how the route is matched, the request's, the answer's and
# the status the answer schema applies to)
ROUTES: list[tuple[str, Callable[[str], bool], str | None, str | None, int]] = [
    ("POST", lambda r: r == "/sessions", "CREATE_SESSION", "SESSION_INFO", 201),
    ("POST", lambda r: r.endswith("/extend"), "EXTEND_SESSION", "SESSION_INFO", 200),
    ("POST", lambda r: r == "/retrieve-sessions", "RETRIEVE_SESSIONS", "RETRIEVE_SESSIONS_OUTPUT", 200),
    ("GET", lambda r: True, None, "SESSION_INFO", 200),
]


def check(method: str, path: str, sent: Any, status: int, answer: Any, *, requests: bool = True) -> None:
    """One exchange against the spec's schemas (`requests`: the request too); raises AssertionError naming
    the violation."""

    def fits(name: str, value: Any) -> None:
        problem = schema.problem(getattr(schema, name), value)
        assert problem is None, f"{method} {path} -> {status}: {name}: {problem}\n{json.dumps(value)[:600]}"

    route = path.removeprefix("/quality-on-demand/v1")
    if route == path:
        return  # not the QoD API (counters, events, token)
    if status >= 400:
        fits("ERROR_INFO", answer)
        assert answer["status"] == status
    if method == "DELETE":
        assert status in (204, 404), status
        assert status == 404 or answer is None
        return
    for verb, matches, request_schema, answer_schema, ok in ROUTES:
        if verb == method and matches(route):
            if request_schema is not None and requests:
                fits(request_schema, sent)
            if answer_schema is not None and status == ok:
                fits(answer_schema, answer)
            return


@dataclass
class Operator:
    """The emulated cell in this process: its control API on a free port, every exchange kept."""

    port: int = 0
    exchanges: list[tuple[str, str, Any, int, Any]] = field(default_factory=list)
    final: dict[str, Any] = field(default_factory=dict)

    @property
    def root(self) -> str:
        return f"http://127.0.0.1:{self.port}/quality-on-demand/v1"

    def record(self, method: str, path: str, sent: Any, status: int, answer: Any) -> None:
        self.exchanges.append((method, path, sent, status, answer))

    def camara(self, **changes: Any) -> CamaraConfig:
        return replace(CamaraConfig(api_root=self.root, timeout_s=2.0), **changes)

    async def counters(self) -> dict[str, Any]:
        async with aiohttp.ClientSession() as http, http.get(f"http://127.0.0.1:{self.port}/counters") as r:
            out: dict[str, Any] = await r.json()
            return out

    async def granted(self) -> bool:
        return bool((await self.counters())["bearers"]["uav1-priority"]["granted"])


@contextlib.asynccontextmanager
async def emulated_operator(
    requests_valid: bool = True,
    client_key: Any = None,
    api_headers: dict[str, str] | None = None,
    **cell: Any,
) -> AsyncIterator[Operator]:
    cfg = CellConfig(
        **{"qod": True, "control_port": 0, "default_listen_port": 0, "priority_listen_port": 0,
           "qod_setup_s": 0.05, **cell}
    )  # fmt: skip
    rig = Operator()
    ready: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
    stop = asyncio.Event()
    task = asyncio.create_task(
        run_cell(
            cfg, cfg.bearer_list(ZenohConfig(), "uav1"), ready=ready.set_result, qod_devices={"uav1": DEVICE},
            qod_client=("dynqos-test", SECRET), qod_client_key=client_key, qod_api_headers=api_headers,
            tap=rig.record, stop=stop,
        )
    )  # fmt: skip
    rig.port = (await asyncio.wait_for(ready, 10))["control_port"]
    try:
        yield rig
    finally:
        stop.set()
        rig.final = await asyncio.wait_for(task, 10)
        for exchange in rig.exchanges:
            check(*exchange, requests=requests_valid)
        if not camara_spec.available():  # the official documents, where this checkout has them
            found = [p for e in rig.exchanges for p in camara_spec.problems(*e, request=requests_valid)]
            assert not found, "\n".join(found[:10])


async def until(probe: Callable[[], Awaitable[bool]], timeout_s: float = 5.0) -> None:
    """Poll the API (the thing under test) until `probe` holds; fail after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not await probe():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.02)  # the polling interval of a client of this API


def run(coro: Awaitable[None]) -> None:
    asyncio.run(asyncio.wait_for(coro, 45))  # type: ignore[arg-type]


def test_create_poll_to_available_extend_and_delete_grant_the_bearer_while_it_lives() -> None:
    async def main() -> None:
        async with emulated_operator() as op, qod_api(op.camara()) as client:
            created = await client.create(session_body())
            assert created.qos_status == "REQUESTED"
            assert not await op.granted()
            sid = created.session_id

            async def available() -> bool:
                return (await client.get(sid)).qos_status == "AVAILABLE"

            await until(available)
            info = await client.get(sid)
            assert 55 < (info.expires_in_s or 0) <= 60
            assert await op.granted()  # the priority bearer has its weight only now
            extended = await client.extend(sid, 30)
            assert extended.raw["duration"] == 90
            assert 85 < (extended.expires_in_s or 0) <= 90
            assert [s.session_id for s in await client.retrieve(DEVICE)] == [sid]
            await client.delete(sid)
            assert not await op.granted()
            with pytest.raises(OperatorError) as gone:
                await client.get(sid)
            assert gone.value.status == 404
        assert op.final["qod"]["created"] == 1
        assert op.final["qod"]["extended"] == 1
        assert op.final["qod"]["deleted"] == 1
        assert op.final["qod"]["sessions"] == []

    run(main())


def test_a_second_session_for_the_flow_is_a_409_and_retrieve_finds_the_first() -> None:
    async def main() -> None:
        async with emulated_operator() as op, qod_api(op.camara()) as client:
            first = await client.create(session_body())
            with pytest.raises(OperatorError) as conflict:
                await client.create(session_body())
            assert conflict.value.status == 409
            assert conflict.value.code == "CONFLICT"
            found = await client.retrieve(DEVICE)
            assert [s.session_id for s in found] == [first.session_id]
            assert found[0].server_ports() == [7448]
            await client.delete(first.session_id)

    run(main())


@pytest.mark.parametrize(
    ("changes", "status", "code"),
    [
        ({"qosProfile": "QOS_NOT_OFFERED"}, 422, "QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE"),
        ({"device": {"phoneNumber": "+46799999999"}}, 404, "IDENTIFIER_NOT_FOUND"),
        ({"applicationServer": {"ipv4Address": "192.0.2.1"}}, 400, "INVALID_ARGUMENT"),
    ],
)
def test_what_the_operator_refuses_is_an_error_with_its_code_and_no_retry(
    changes: dict[str, Any], status: int, code: str
) -> None:
    async def main() -> None:
        async with emulated_operator() as op, qod_api(op.camara()) as client:
            with pytest.raises(OperatorError) as refused:
                await client.create(session_body(**changes))
            assert (refused.value.status, refused.value.code) == (status, code)
            assert not refused.value.transient
            assert client.operator.retries == 0
        assert op.final["qod"]["sessions"] == []

    run(main())


@pytest.mark.parametrize(
    "changes",
    [
        {"duration": 0},
        {"device": {"phoneNumber": "0700"}},
        {"qosProfile": None},
        {"applicationServerPorts": {}},
        {"sink": "http://203.0.113.9/notify"},  # https only, except on loopback (the demo's sink)
        {"colour": "red"},  # a field the API does not have, at the top
        {"device": {"phoneNumber": "+46700000001", "imei": "35209900176148"}},  # or inside an object
        {"applicationServer": {"ipv4Address": "127.0.0.1", "port": 7448}},
    ],
)
def test_the_emulator_answers_a_request_outside_the_spec_with_400(changes: dict[str, Any]) -> None:
    async def main() -> None:
        async with emulated_operator(requests_valid=False) as op, aiohttp.ClientSession() as http:
            body = {k: v for k, v in session_body(**changes).items() if v is not None}
            async with http.post(op.root + "/sessions", json=body) as r:
                answer = await r.json()
                assert (r.status, answer["code"]) == (400, "INVALID_ARGUMENT")
        assert op.final["qod"]["created"] == 0

    run(main())


def test_an_expired_token_is_refreshed_once_and_the_call_retried() -> None:
    async def main(tmp: Path) -> None:
        async with emulated_operator(qod_auth=True) as op:
            secret_file = tmp / "secret"
            secret_file.write_text(SECRET + "\n")
            cfg = op.camara(
                token_url=f"http://127.0.0.1:{op.port}/oauth2/token", client_id="dynqos-test",
                client_secret_file=str(secret_file),
            )  # fmt: skip
            async with qod_api(cfg) as client:
                created = await client.create(session_body())
                assert client.operator.token_refreshes == 1
                async with aiohttp.ClientSession() as http:  # the operator revokes every token
                    await http.delete(f"http://127.0.0.1:{op.port}/oauth2/tokens")
                info = await client.get(created.session_id)
                assert info.session_id == created.session_id
                assert client.operator.token_refreshes == 2
                await client.delete(created.session_id)
            async with (
                aiohttp.ClientSession() as http,
                http.get(op.root + f"/sessions/{created.session_id}") as r,
            ):
                assert r.status == 401  # no token, no answer
        statuses = [(m, p.rsplit("/", 1)[-1], s) for m, p, _, s, _ in op.exchanges]
        assert ("GET", created.session_id, 401) in statuses
        assert ("GET", created.session_id, 200) in statuses

    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        run(main(Path(tmp)))


def test_sessions_expire_and_the_network_can_end_them_with_a_notification() -> None:
    async def main() -> None:
        events: list[dict[str, Any]] = []
        got = asyncio.Event()

        async def sink(request: web.Request) -> web.Response:
            events.append(json.loads(await request.read()))
            got.set()
            return web.Response(status=204)

        app = web.Application()
        app.router.add_post("/sink", sink)
        runner = web.AppRunner(app)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        sink_url = f"http://127.0.0.1:{runner.addresses[0][1]}/sink"
        try:
            async with emulated_operator() as op, qod_api(op.camara()) as client:
                short = await client.create(session_body(duration=1))

                async def ended() -> bool:
                    return (await client.get(short.session_id)).qos_status == "UNAVAILABLE"

                await until(ended)
                assert (await client.get(short.session_id)).status_info == "DURATION_EXPIRED"
                assert not await op.granted()
                await client.delete(short.session_id)
                long = await client.create(session_body(sink=sink_url))
                await asyncio.wait_for(got.wait(), 5)  # AVAILABLE, notified
                got.clear()
                async with aiohttp.ClientSession() as http:
                    await http.post(
                        f"http://127.0.0.1:{op.port}/events", json={"kind": "qod_end", "uav": "uav1"}
                    )
                await asyncio.wait_for(got.wait(), 5)
                info = await client.get(long.session_id)
                assert (info.qos_status, info.status_info) == ("UNAVAILABLE", "NETWORK_TERMINATED")
                assert not await op.granted()
                with pytest.raises(OperatorError) as conflict:  # its resources stay until deleted
                    await client.create(session_body())
                assert conflict.value.status == 409
                await client.delete(long.session_id)
        finally:
            await runner.cleanup()
        for event in events:
            assert schema.problem(schema.QOS_STATUS_CHANGED, event) is None
        assert [e["data"]["qosStatus"] for e in events] == ["AVAILABLE", "UNAVAILABLE"]
        assert events[1]["data"]["statusInfo"] == "NETWORK_TERMINATED"

    run(main())


def test_an_operator_that_cannot_grant_ends_the_request_network_terminated() -> None:
    async def main() -> None:
        async with emulated_operator(qod_max_sessions=0) as op, qod_api(op.camara()) as client:
            created = await client.create(session_body())

            async def settled() -> bool:
                return (await client.get(created.session_id)).qos_status != "REQUESTED"

            await until(settled)
            info = await client.get(created.session_id)
            assert (info.qos_status, info.status_info) == ("UNAVAILABLE", "NETWORK_TERMINATED")
            assert not await op.granted()
            await client.delete(created.session_id)
        assert op.final["qod"]["refused"] == 1

    run(main())


# ---- what only a scripted operator does: throttle, fail, hang -------------------------------------------


correlators: list[str] = []  # what the scripted operator last saw


@contextlib.asynccontextmanager
async def scripted(
    answers: list[tuple[int, dict[str, str], Any, float]],
) -> AsyncIterator[tuple[str, list[str]]]:
    """A server answering POST /sessions with the scripted (status, headers, body, delay_s), in turn; it
    keeps each answer's status and the x-correlator of the request it answered (`scripted.correlators`)."""
    seen: list[str] = []
    correlators.clear()

    async def handler(request: web.Request) -> web.Response:
        sent = await request.json()
        assert schema.problem(schema.CREATE_SESSION, sent) is None
        status, headers, body, delay = answers[min(len(seen), len(answers) - 1)]
        seen.append(f"{status}")
        correlators.append(request.headers.get("x-correlator", ""))
        await asyncio.sleep(delay)  # a slow operator
        return web.json_response(body, status=status, headers=headers)

    app = web.Application()
    app.router.add_post("/qod/sessions", handler)
    runner = web.AppRunner(app)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", 0).start()
    try:
        yield f"http://127.0.0.1:{runner.addresses[0][1]}/qod", seen
    finally:
        await runner.cleanup()


SESSION = {
    "sessionId": "6f0d8f5e-1c7c-4d5b-9b1e-2a9d7c3e4f50", "duration": 60, "qosStatus": "REQUESTED",
    "applicationServer": {"ipv4Address": "127.0.0.1"}, "qosProfile": "QOS_E",
}  # fmt: skip
BUSY = {"status": 429, "code": "TOO_MANY_REQUESTS", "message": "slow down"}
DOWN = {"status": 503, "code": "UNAVAILABLE", "message": "maintenance"}


def test_429_and_5xx_are_retried_with_backoff_then_succeed() -> None:
    async def main() -> None:
        script = [(429, {"Retry-After": "0.05"}, BUSY, 0.0), (503, {}, DOWN, 0.0), (201, {}, SESSION, 0.0)]
        async with (
            scripted(script) as (root, seen),
            qod_api(CamaraConfig(api_root=root, timeout_s=3)) as client,
        ):
            info = await client.create(session_body())
            assert info.session_id == SESSION["sessionId"]
            assert seen == ["429", "503", "201"]
            assert client.operator.retries == 2

    run(main())


def test_a_failing_operator_is_a_transient_error_within_the_timeout_naming_its_correlator() -> None:
    async def main() -> None:
        async with (
            scripted([(503, {}, DOWN, 0.0)]) as (root, seen),
            qod_api(CamaraConfig(api_root=root, timeout_s=2)) as client,
        ):
            with pytest.raises(OperatorError) as failed:
                await client.create(session_body())
            assert failed.value.status == 503
            assert failed.value.transient
            assert failed.value.kind == "server"
            assert len(seen) == 4  # the first try and three retries
            first = list(correlators)
            assert len(set(first)) == 1  # one x-correlator across the retries of one call
            uuid.UUID(first[0])
            assert failed.value.correlator == first[0]
            assert first[0] in str(failed.value)
            with pytest.raises(OperatorError):
                await client.create(session_body())
            assert correlators[-1] != first[0]  # a new call, a new correlator

    run(main())


@pytest.mark.parametrize(
    ("status", "kind", "transient"),
    [
        (0, "unreachable", True),
        (429, "throttled", True),
        (500, "server", True),
        (503, "server", True),
        (401, "credentials", False),
        (403, "forbidden", False),
        (404, "not_found", False),
        (409, "conflict", False),
        (400, "refused", False),
        (422, "refused", False),
    ],
)
def test_an_error_says_its_kind_and_whether_asking_again_may_help(
    status: int, kind: str, transient: bool
) -> None:
    error = OperatorError(status, "CODE", "message", correlator="c-1")
    assert (error.kind, error.transient) == (kind, transient)


def test_a_hanging_operator_is_cut_off_at_the_timeout() -> None:
    async def main() -> None:
        async with (
            scripted([(201, {}, SESSION, 5.0)]) as (root, _),
            qod_api(CamaraConfig(api_root=root, timeout_s=0.3)) as client,
        ):
            started = time.monotonic()
            with pytest.raises(OperatorError) as hung:
                await client.create(session_body())
            assert hung.value.status == 0
            assert hung.value.code == "TIMEOUT"
            assert time.monotonic() - started < 2.0  # bounded by timeout_s, not by the operator

    run(main())


def test_a_retry_after_longer_than_the_call_is_handed_to_the_agent_in_seconds_or_as_a_date() -> None:
    assert retry_after_s("120") == 120.0
    assert retry_after_s("Wed, 21 Oct 2015 07:28:00 GMT", now_unix=1445412430.0) == pytest.approx(50.0)
    assert retry_after_s("Wed, 21 Oct 2015 07:28:00 GMT", now_unix=1445412530.0) == 0.0  # in the past
    assert retry_after_s("soon") is None
    assert retry_after_s(None) is None

    async def main() -> None:
        async with (
            scripted([(429, {"Retry-After": "30"}, BUSY, 0.0)]) as (root, seen),
            qod_api(CamaraConfig(api_root=root, timeout_s=1)) as client,
        ):
            with pytest.raises(OperatorError) as throttled:
                await client.create(session_body())
            assert seen == ["429"]  # 30 s does not fit in the call's 1 s: not retried within it
            assert throttled.value.retry_after_s == 30.0
            assert throttled.value.transient

    run(main())


def test_a_failing_token_endpoint_is_transient_and_refused_credentials_are_not(tmp_path: Path) -> None:
    async def main() -> None:
        async def token(request: web.Request) -> web.Response:
            secret = (await request.post()).get("client_secret")
            if secret == "wrong":
                return web.json_response({"error": "invalid_client"}, status=401)
            return web.json_response({"error": "down"}, status=503)

        app = web.Application()
        app.router.add_post("/token", token)
        runner = web.AppRunner(app)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", 0).start()
        url = f"http://127.0.0.1:{runner.addresses[0][1]}"
        try:
            for secret, status, transient in (("right", 503, True), ("wrong", 401, False)):
                secret_file = tmp_path / f"secret-{secret}"
                secret_file.write_text(secret)
                cfg = CamaraConfig(
                    api_root=f"{url}/qod", token_url=f"{url}/token", client_id="c",
                    client_secret_file=str(secret_file), timeout_s=1,
                )  # fmt: skip
                async with qod_api(cfg) as client:
                    with pytest.raises(OperatorError) as failed:
                        await client.create(session_body())
                assert (failed.value.status, failed.value.transient) == (status, transient)
        finally:
            await runner.cleanup()

    run(main())


def test_the_agents_profile_check_and_the_profiles_api_fit_the_official_document() -> None:
    """The QoS Profiles API as the agent reads it (and by name, found or not): each exchange is checked
    against qos-profiles 1.1.0 by the fixture when the official documents are here."""

    async def main() -> None:
        async with emulated_operator(qod_max_duration_s=20, qod_inactive_profiles=("QOS_M",)) as op:
            async with qod_api(op.camara(duration_s=600, extend_before_s=30)) as client:
                fitted = await ProfileWatch(client.operator, client.operator.cfg).start()
            assert (fitted.duration_s, fitted.extend_before_s, fitted.renew_before_s) == (20, 10.0, 2.0)
            root = f"http://127.0.0.1:{op.port}/qos-profiles/v1/qos-profiles"
            async with aiohttp.ClientSession() as http:
                async with http.get(f"{root}/QOS_M") as found:
                    assert (found.status, (await found.json())["status"]) == (200, "INACTIVE")
                async with http.get(f"{root}/QOS_X") as missing:
                    assert (missing.status, (await missing.json())["code"]) == (404, "NOT_FOUND")
        paths = [path for _, path, *_ in op.exchanges]
        assert "/qos-profiles/v1/retrieve-qos-profiles" in paths

    run(main())


def test_the_official_documents_flag_what_breaks_them() -> None:
    """The checker itself: an answer outside the spec and a status it does not list are found."""
    if why := camara_spec.available():
        pytest.skip(why)
    body = session_body()
    good = body | {"sessionId": str(uuid.uuid4()), "qosStatus": "REQUESTED"}
    assert camara_spec.problems("POST", "/quality-on-demand/v1/sessions", body, 201, good) == []
    assert camara_spec.problems(
        "POST", "/quality-on-demand/v1/sessions", body, 201, good | {"qosStatus": "OK"}
    )
    teapot = {"status": 418, "code": "TEAPOT", "message": "no"}
    assert camara_spec.problems("POST", "/quality-on-demand/v1/sessions", body, 418, teapot)
    profile = {"name": "QOS_E", "status": "ACTIVE", "maxDuration": {"value": 0, "unit": "Seconds"}}
    assert camara_spec.problems("POST", "/qos-profiles/v1/retrieve-qos-profiles", {}, 200, [profile])
    remote_sink = body | {"sink": "http://203.0.113.9/notify"}  # only loopback is a known deviation
    found = camara_spec.problems("POST", "/quality-on-demand/v1/sessions", remote_sink, 201, good)
    assert any(": request: " in p for p in found), found


def test_the_x_correlator_is_echoed_and_a_malformed_one_refused() -> None:
    async def main() -> None:
        async with emulated_operator(requests_valid=False) as op, aiohttp.ClientSession() as http:
            mine = {"x-correlator": "b4333c46-49c0-4f62-80d7-f0ef930f1c46"}
            async with http.post(op.root + "/retrieve-sessions", json={"device": DEVICE}, headers=mine) as r:
                assert (r.status, r.headers.get("x-correlator")) == (200, mine["x-correlator"])
            async with http.post(op.root + "/retrieve-sessions", json={"device": DEVICE},
                                 headers={"x-correlator": "no spaces allowed"}) as r:  # fmt: skip
                assert (r.status, (await r.json())["code"]) == (400, "INVALID_ARGUMENT")
            async with http.post(op.root + "/retrieve-sessions", json={"device": DEVICE}) as r:
                assert r.status == 200
                assert "x-correlator" not in r.headers  # none sent, none echoed

    run(main())


def test_too_many_sessions_is_a_429_with_retry_after(monkeypatch: pytest.MonkeyPatch) -> None:
    from dynqos.sim.network import operator

    monkeypatch.setattr(operator, "MAX_SESSIONS", 1)

    async def main() -> None:
        async with emulated_operator() as op, aiohttp.ClientSession() as http:
            async with http.post(op.root + "/sessions", json=session_body()) as r:
                assert r.status == 201
            other_port = session_body(applicationServerPorts={"ports": [7449]})
            async with http.post(op.root + "/sessions", json=other_port) as r:
                assert (r.status, r.headers.get("Retry-After")) == (429, "5")
            async with qod_api(op.camara(timeout_s=0.5)) as client:
                with pytest.raises(OperatorError) as throttled:
                    await client.create(other_port)
            assert (throttled.value.status, throttled.value.retry_after_s) == (429, 5.0)  # too long to wait

    run(main())


def test_a_device_by_nai_alone_is_unsupported_and_ipv6_matches_within_its_64() -> None:
    from dynqos.sim.network.operator import Operator as Emulated

    devices = {"uav1": {"phoneNumber": "+46700000001", "ipv6Address": "2001:db8:85a3:8d3:1319:8a2e:370:7344"}}
    op = Emulated(
        CellConfig(qod=True), devices, {"uav1": "127.0.0.1"}, monotonic=lambda: 0.0, wall=lambda: 0.0
    )
    nai = op.create(session_body(device={"networkAccessIdentifier": "uav1@example.com"}))[0]
    assert (nai.status, nai.body["code"]) == (422, "UNSUPPORTED_IDENTIFIER")
    both = op.retrieve(
        {"device": {"networkAccessIdentifier": "uav1@example.com", "phoneNumber": "+46700000001"}}
    )
    assert both.status == 200  # the phone number names it; the NAI is not looked at
    same_64 = op.retrieve({"device": {"ipv6Address": "2001:db8:85a3:8d3::"}})
    assert same_64.status == 200
    other_64 = op.retrieve({"device": {"ipv6Address": "2001:db8:85a3:8d4::1"}})
    assert (other_64.status, other_64.body["code"]) == (404, "IDENTIFIER_NOT_FOUND")


def test_the_sink_credential_the_agent_sends_fits_the_document_and_is_never_echoed() -> None:
    from dynqos.edge.qos.sink import SinkGuard

    async def main() -> None:
        credential = SinkGuard().credential(60, time.time())
        async with emulated_operator() as op, qod_api(op.camara()) as client:
            body = session_body(sink=f"http://127.0.0.1:{op.port}/nowhere", sinkCredential=credential)
            created = await client.create(body)
            assert "sinkCredential" not in created.raw  # a secret the operator keeps
            await client.delete(created.session_id)

    run(main())


def _ec_key(path: Path) -> Any:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    key = ec.generate_private_key(ec.SECP256R1())
    pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    path.write_bytes(pem)
    return key


def test_private_key_jwt_gets_a_token_with_a_signed_assertion_and_a_foreign_key_none(tmp_path: Path) -> None:
    registered = _ec_key(tmp_path / "client.pem")
    _ec_key(tmp_path / "stranger.pem")

    async def main() -> None:
        async with emulated_operator(qod_auth=True, client_key=registered.public_key()) as op:
            token_url = f"http://127.0.0.1:{op.port}/oauth2/token"
            mine = op.camara(
                token_url=token_url, client_id="dynqos-test", client_key_file=str(tmp_path / "client.pem")
            )
            async with qod_api(mine) as client:
                created = await client.create(session_body())
                await client.delete(created.session_id)
                form = client.operator._token_form()
            assert "client_secret" not in form
            assert form["client_assertion_type"] == "urn:ietf:params:oauth:client-assertion-type:jwt-bearer"
            async with aiohttp.ClientSession() as http:
                async with http.post(token_url, data=form) as first:
                    assert first.status == 200
                async with http.post(token_url, data=form) as replayed:
                    assert replayed.status == 401  # an assertion is used once (jti)
            stranger = replace(mine, client_key_file=str(tmp_path / "stranger.pem"))
            async with qod_api(stranger) as client:
                with pytest.raises(OperatorError) as refused:
                    await client.create(session_body())
            assert (refused.value.status, refused.value.code) == (401, "TOKEN")
            assert settings_at_fault(refused.value)  # one error line naming the setting, no retries

    run(main())


def test_a_token_without_the_calls_scope_is_a_403_that_names_the_setting(tmp_path: Path) -> None:
    secret_file = tmp_path / "secret"
    secret_file.write_text(SECRET)

    async def main() -> None:
        async with emulated_operator(qod_auth=True) as op:
            narrow = op.camara(
                token_url=f"http://127.0.0.1:{op.port}/oauth2/token", client_id="dynqos-test",
                client_secret_file=str(secret_file), scope="quality-on-demand:sessions:read",
            )  # fmt: skip
            async with qod_api(narrow) as client:
                with pytest.raises(OperatorError) as denied:
                    await client.create(session_body())
                assert (denied.value.status, denied.value.code) == (403, "PERMISSION_DENIED")
                assert "scopes" in (settings_at_fault(denied.value) or "")
                with pytest.raises(OperatorError) as unknown:  # the scope it has lets a read through
                    await client.get(str(uuid.uuid4()))
                assert unknown.value.status == 404
                with pytest.raises(OperatorError) as by_device:
                    await client.retrieve(DEVICE)
                assert by_device.value.status == 403
        assert op.final["qod"]["created"] == 0

    run(main())


def test_an_aggregators_fixed_api_key_headers_instead_of_a_token(tmp_path: Path) -> None:
    keys_file = tmp_path / "headers"
    keys_file.write_text("# the aggregator's keys\nX-API-Key: k3y-for-tests\nX-API-Host: qod.example\n")
    (tmp_path / "wrong").write_text("X-API-Key: guessed\nX-API-Host: qod.example\n")

    async def main() -> None:
        wanted = {"X-API-Key": "k3y-for-tests", "X-API-Host": "qod.example"}
        async with emulated_operator(qod_auth=True, api_headers=wanted) as op:
            async with qod_api(op.camara(headers_file=str(keys_file))) as client:
                created = await client.create(session_body())
                await client.delete(created.session_id)
            async with qod_api(op.camara(headers_file=str(tmp_path / "wrong"))) as client:
                with pytest.raises(OperatorError) as refused:
                    await client.create(session_body())
            assert refused.value.status == 401
            assert settings_at_fault(refused.value)
        assert op.final["qod"]["created"] == 1

    run(main())


def test_three_legged_a_token_per_device_and_bodies_that_name_none(tmp_path: Path) -> None:
    from dynqos.edge.operator.client import SUBJECT

    registered = _ec_key(tmp_path / "client.pem")

    async def main() -> None:
        async with emulated_operator(qod_auth=True, client_key=registered.public_key()) as op:
            token_url = f"http://127.0.0.1:{op.port}/oauth2/token"
            cfg = op.camara(token_url=token_url, client_id="dynqos-test",
                            client_key_file=str(tmp_path / "client.pem"), three_legged=True)  # fmt: skip
            body = {k: v for k, v in session_body().items() if k != "device"}
            async with qod_api(cfg) as client:
                SUBJECT.set(f"tel:{DEVICE['phoneNumber']}")
                created = await client.create(body)
                assert "device" not in created.raw  # the token names it; the answer does not repeat it
                assert [s.session_id for s in await client.retrieve(None)] == [created.session_id]
                with pytest.raises(OperatorError) as named:
                    await client.create(session_body())  # device in the body as well
                assert (named.value.status, named.value.code) == (422, "UNNECESSARY_IDENTIFIER")
                await client.delete(created.session_id)
                SUBJECT.set("tel:+46799999999")  # a phone the operator does not know: no token
                with pytest.raises(OperatorError) as stranger:
                    await client.create(body)
                assert (stranger.value.status, stranger.value.code) == (401, "TOKEN")
        assert op.final["qod"]["created"] == 1

    run(main())
