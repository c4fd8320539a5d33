"""Schemathesis, from CAMARA's own OpenAPI documents, against the emulated operator (`dynqos sim cell`
as a process on 127.0.0.1): requests generated from the documents' schemas, valid and not, find no
server error and no answer outside the documents (status, content type, body). The documents are read
from ../shared/camara; without them (or without schemathesis) this skips and says why."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import pytest

from tests import camara_spec
from tests.conftest import free_tcp_port
from tests.procs import DynqosProcess

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

EXAMPLES = 30  # per operation, at most: a bounded run (7 operations in the two documents)
APIS = {"quality-on-demand.yaml": "/quality-on-demand/v1", "qos-profiles.yaml": "/qos-profiles/v1"}


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    if why := camara_spec.available():
        pytest.skip(why)
    pytest.importorskip("schemathesis", reason="schemathesis is not installed (pip install -e '.[dev]')")
    port = free_tcp_port()
    config = tmp_path_factory.mktemp("fuzz") / "cell.toml"
    config.write_text(
        f"[cell]\nqod = true\ncontrol_port = {port}\ndefault_listen_port = 0\npriority_listen_port = 0\n"
        '[qos.camara.devices]\nuav1 = { phoneNumber = "+46700000001" }\n'
    )
    proc = DynqosProcess(["sim", "cell"], config)
    try:
        yield port
    finally:
        log = proc.stop()
        assert "Traceback" not in log, log[-3000:]


@pytest.mark.parametrize("document", sorted(APIS))
def test_generated_requests_find_no_server_error_and_no_answer_outside_the_document(
    cell: int, document: str
) -> None:
    import schemathesis
    from hypothesis import HealthCheck, given, settings
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        response_schema_conformance,
        status_code_conformance,
    )

    schema = schemathesis.openapi.from_path(str(camara_spec.CAMARA / document))
    base_url = f"http://127.0.0.1:{cell}{APIS[document]}"
    checks = [
        not_a_server_error,
        status_code_conformance,
        content_type_conformance,
        response_schema_conformance,
    ]
    operations = [result.ok() for result in schema.get_all_operations()]
    assert operations
    calls = 0
    for operation in operations:

        @settings(max_examples=EXAMPLES, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))  # fmt: skip
        @given(case=operation.as_strategy())
        def one(case: Any) -> None:
            nonlocal calls
            calls += 1
            case.call_and_validate(base_url=base_url, checks=checks, headers={"x-correlator": "fuzz"})

        one()
    assert calls >= len(operations) * 5


def test_a_method_a_resource_does_not_take_is_405_with_the_methods_it_takes(cell: int) -> None:
    """RFC 9110: a 405 names the allowed methods in `Allow` (schemathesis's undeclared-method check
    asks for it), in CAMARA's error shape for the APIs, and for the cell's own controls too."""
    import urllib.error
    import urllib.request

    def answer(method: str, path: str) -> tuple[int, str, dict[str, Any]]:
        request = urllib.request.Request(f"http://127.0.0.1:{cell}{path}", method=method, data=b"{}",
                                         headers={"Content-Type": "application/json"})  # fmt: skip
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, response.headers.get("Allow", ""), json.loads(response.read())
        except urllib.error.HTTPError as exc:
            return exc.code, exc.headers.get("Allow", ""), json.loads(exc.read())

    status, allow, body = answer("PUT", "/quality-on-demand/v1/sessions")
    assert (status, allow, body["code"]) == (405, "POST", "METHOD_NOT_ALLOWED")
    status, allow, body = answer("PATCH", "/quality-on-demand/v1/sessions/abc")
    assert status == 405
    assert set(allow.split(",")) == {"GET", "HEAD", "DELETE"}
    status, allow, _ = answer("DELETE", "/counters")
    assert (status, set(allow.split(","))) == (405, {"GET", "HEAD"})
