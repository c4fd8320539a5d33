"""TLS to the operator (edge/operator/client.py): the agent verifies the operator with `ca_file` and shows
its own certificate (`tls_cert_file`, `tls_key_file`) to an operator that wants mutual TLS. A scripted
operator over real TLS on 127.0.0.1, with certificates from `dynqos certs` (common/certs.py)."""

from __future__ import annotations

import asyncio
import ssl
from pathlib import Path

import pytest
from aiohttp import web

from dynqos.common.certs import make_dev_pki
from dynqos.common.config import CamaraConfig
from dynqos.common.errors import ConfigError
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.profiles import ProfilesApi
from tests.conftest import free_tcp_port
from tests.operator_apis import qod_api

pytestmark = pytest.mark.timeout(30)


def test_mutual_tls_with_the_operators_ca_and_a_client_certificate(tmp_path: Path) -> None:
    issued = make_dev_pki(tmp_path, [], [])
    server, client_pair = issued["router"], issued["edge-qos"]
    ca = str(tmp_path / "ca.pem")

    async def main() -> None:
        app = web.Application()

        async def profiles(_: web.Request) -> web.Response:
            return web.json_response([])

        app.router.add_post("/qos-profiles/v1/retrieve-qos-profiles", profiles)
        tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH, cafile=ca)
        tls.load_cert_chain(server.cert, server.key)
        tls.verify_mode = ssl.CERT_REQUIRED  # the operator wants our certificate
        runner = web.AppRunner(app)
        await runner.setup()
        port = free_tcp_port()
        await web.TCPSite(runner, "127.0.0.1", port, ssl_context=tls).start()
        root = f"https://127.0.0.1:{port}/quality-on-demand/v1"
        try:
            mine = CamaraConfig(api_root=root, ca_file=ca, tls_cert_file=str(client_pair.cert),
                                tls_key_file=str(client_pair.key), timeout_s=2)  # fmt: skip
            async with qod_api(mine) as client:
                assert await ProfilesApi(client.operator).retrieve() == []
            for cfg, why in (
                (CamaraConfig(api_root=root, ca_file=ca, timeout_s=2), "no client certificate"),
                (CamaraConfig(api_root=root, timeout_s=2), "the system does not trust the operator's CA"),
            ):
                async with qod_api(cfg) as client:
                    with pytest.raises(OperatorError) as refused:
                        await ProfilesApi(client.operator).retrieve()
                assert (refused.value.status, refused.value.code) == (0, "UNREACHABLE"), why
        finally:
            await runner.cleanup()

    asyncio.run(asyncio.wait_for(main(), 20))


def test_tls_files_that_do_not_load_are_named_at_start(tmp_path: Path) -> None:
    (tmp_path / "junk.pem").write_text("not a certificate\n")
    with pytest.raises(ConfigError, match=r"qos\.camara\.ca_file"):
        OperatorClient(CamaraConfig(api_root="https://a.example/qod", ca_file=str(tmp_path / "junk.pem")))
    junk = str(tmp_path / "junk.pem")
    with pytest.raises(ConfigError, match=r"qos\.camara\.tls_cert_file"):
        OperatorClient(CamaraConfig(api_root="https://a.example/qod", tls_cert_file=junk, tls_key_file=junk))
    with pytest.raises(ConfigError, match="go together"):
        CamaraConfig(tls_cert_file="a.pem")
