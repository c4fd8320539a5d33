"""The emulated NEF served by the cell's control API (`[cell] nef = true`), flown by dynqos's own NEF
client (edge/operator/nef.py) over real HTTP on 127.0.0.1: a subscription gives the drone's priority
bearer its weight while it lives, its notifications and QoS monitoring reports reach the sink, and every
exchange is what TS 29.122's document describes (where ../shared/3gpp has it)."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any

import aiohttp
import pytest
from aiohttp import web

from dynqos.common.config import CamaraConfig, CellConfig, ZenohConfig
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.nef import API, FlowRule, Monitoring, NefApi, SubscriptionRequest
from dynqos.sim.network.service import run_cell
from tests import nef_spec

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

UE = "10.45.0.7"
DEVICE = {"phoneNumber": "+46700000001", "ipv4Address": {"privateAddress": UE}}


@asynccontextmanager
async def cell_with_nef(**cell: Any) -> AsyncIterator[tuple[int, list[tuple[Any, ...]]]]:
    """The cell in this process with QoD and the NEF on; its control port and every exchange."""
    cfg = CellConfig(
        **{
            "qod": True,
            "nef": True,
            "control_port": 0,
            "default_listen_port": 0,
            "priority_listen_port": 0,
            "qod_setup_s": 0.05,
            **cell,
        }
    )
    exchanges: list[tuple[Any, ...]] = []
    ready: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
    stop = asyncio.Event()
    bearers = cfg.bearer_list(ZenohConfig(), "uav1")
    task = asyncio.create_task(
        run_cell(
            cfg,
            bearers,
            ready=ready.set_result,
            qod_devices={"uav1": DEVICE},
            tap=lambda *exchange: exchanges.append(exchange),
            stop=stop,
        )
    )
    port = (await asyncio.wait_for(ready, 10))["control_port"]
    try:
        yield port, exchanges
    finally:
        stop.set()
        await asyncio.wait_for(task, 10)


@asynccontextmanager
async def sink() -> AsyncIterator[tuple[str, list[dict[str, Any]]]]:
    heard: list[dict[str, Any]] = []

    async def take(request: web.Request) -> web.Response:
        assert request.content_type == "application/json"
        heard.append(json.loads(await request.read()))
        return web.Response(status=204)

    app = web.Application()
    app.router.add_post("/nef", take)
    runner = web.AppRunner(app)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", 0).start()
    try:
        yield f"http://127.0.0.1:{runner.addresses[0][1]}/nef", heard
    finally:
        await runner.cleanup()


async def until(probe: Callable[[], Awaitable[bool]], timeout_s: float = 5.0) -> None:
    """Poll the cell (the thing under test) until `probe` holds; fail after `timeout_s`."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not await probe():
        assert asyncio.get_running_loop().time() < deadline, "timed out"
        await asyncio.sleep(0.02)  # the polling interval of a client of this API


def test_a_subscription_grants_the_priority_bearer_until_the_network_ends_it_and_reports_its_delays() -> None:
    zenoh = ZenohConfig()

    async def main() -> list[tuple[Any, ...]]:
        async with (
            cell_with_nef() as (port, exchanges),
            sink() as (sink_url, heard),
            OperatorClient(CamaraConfig(timeout_s=5.0)) as operator,
            aiohttp.ClientSession() as http,
        ):

            async def counters() -> dict[str, Any]:
                async with http.get(f"http://127.0.0.1:{port}/counters") as answer:
                    out: dict[str, Any] = await answer.json()
                    return out

            async def granted() -> bool:
                return bool((await counters())["bearers"]["uav1-priority"]["granted"])

            api = NefApi(operator, f"http://127.0.0.1:{port}", "af-dynqos")
            ask = SubscriptionRequest(
                ue_ipv4=UE,
                flows=(FlowRule(UE, "127.0.0.1", zenoh.priority_port),),
                qos_reference="QOS_E",
                notification_destination=sink_url,
                monitoring=Monitoring(period_s=1),
            )
            made = await api.create(ask)
            assert (
                made.raw["self"]
                == f"http://127.0.0.1:{port}{API}/af-dynqos/subscriptions/{made.subscription_id}"
            )
            await until(granted)
            assert not (await counters())["bearers"]["uav1-default"]["granted"]
            await until(lambda: _heard(heard, "QOS_MONITORING"), timeout_s=5)
            events = [r["event"] for n in heard for r in n["eventReports"]]
            assert events[:2] == ["SUCCESSFUL_RESOURCES_ALLOCATION", "QOS_GUARANTEED"]
            monitored = next(r for n in heard for r in n["eventReports"] if r["event"] == "QOS_MONITORING")
            (delays,) = monitored["qosMonReports"]
            assert delays["ulDelays"][0] >= CellConfig().base_delay_up_ms
            assert delays["rtDelays"][0] == delays["ulDelays"][0] + delays["dlDelays"][0]
            async with http.post(made.raw["self"], json=made.raw) as post:  # not a method of the resource
                assert post.status == 405
                assert {"GET", "PUT", "PATCH", "DELETE"} <= set(post.headers["Allow"].split(","))
                assert (await post.json())["status"] == 405
            async with http.post(f"http://127.0.0.1:{port}/events", json={"kind": "qod_end", "uav": "uav1"}):
                pass  # the network ends it: the sink hears so and the bearer loses its weight
            await until(lambda: _heard(heard, "SESSION_TERMINATION"))
            assert not await granted()
            await api.delete(made.subscription_id)
            with pytest.raises(OperatorError) as gone:
                await api.get(made.subscription_id)
            assert gone.value.status == 404
            assert (await counters())["nef"]["created"] == 1
            return exchanges

    exchanges = asyncio.run(asyncio.wait_for(main(), 45))
    if not nef_spec.available():
        found = [
            p
            for method, path, sent, status, answer in exchanges
            if path.startswith(API) and status != 405  # a method the document has not: checked above
            for p in nef_spec.problems(
                method,
                path,
                sent if method == "POST" else None,
                status,
                answer,
                headers={"Location": answer["self"]} if status == 201 else None,
            )
        ]
        assert found == []


def _heard(heard: list[dict[str, Any]], event: str) -> Awaitable[bool]:
    async def probe() -> bool:
        return any(r["event"] == event for n in heard for r in n["eventReports"])

    return probe()
