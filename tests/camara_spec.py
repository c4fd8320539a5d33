"""Every exchange with a CAMARA API checked against the official OpenAPI documents (CAMARA release r3.2:
quality-on-demand 1.1.0, qos-profiles 1.1.0), read from ../shared/camara, with openapi-core: the request
as the spec describes it (path, method, body) and the answer for its status (a status the spec does not
list for that operation is itself a finding). Our own schemas (sim/network/operator_schema.py) were
written from the spec by us; these are the documents nobody here wrote."""

from __future__ import annotations

import functools
import json
import re
import warnings
from pathlib import Path
from typing import Any

CAMARA = Path(__file__).resolve().parents[2] / "shared" / "camara"
DOCUMENTS = {
    "/quality-on-demand/v1": "quality-on-demand.yaml",
    "/qos-profiles/v1": "qos-profiles.yaml",
    "/predictive-connectivity-data/v0.1": "predictive-connectivity-data.yaml",
    "/qos-booking/v0.1": "qos-booking.yaml",
}
HOST = "http://127.0.0.1:8080"  # the spec's {apiRoot}: any root matches
# Where dynqos knowingly departs from the documents, each with its reason (docs/qos.md says the same):
# the demo's notification sink is plain HTTP on loopback (no TLS to set up on one laptop), and the spec
# allows only https sinks. A sink anywhere else must be https.
KNOWN_DEVIATIONS = {"an http sink on loopback": re.compile(r"'http://127\.0\.0\.1:\d+/[^']*' does not match")}


def available() -> str:
    """Why the official documents cannot be used ("" when they can)."""
    try:
        import openapi_core  # noqa: F401
    except ModuleNotFoundError:
        return "openapi-core is not installed (pip install -e '.[dev]')"
    missing = [name for name in DOCUMENTS.values() if not (CAMARA / name).is_file()]
    return f"the official CAMARA documents {missing} are absent from {CAMARA}" if missing else ""


@functools.cache
def _api(document: str) -> Any:
    from openapi_core import Config, OpenAPI

    # qos-profiles 1.1.0 gives QosProfileName `format: string`, a format no validator knows: any string
    config = Config(
        extra_format_validators={"string": lambda value: isinstance(value, str)},
        extra_format_unmarshallers={"string": str},
    )
    return OpenAPI.from_file_path(str(CAMARA / document), config=config)


def problems(
    method: str, path: str, sent: Any, status: int, answer: Any, *, request: bool = True
) -> list[str]:
    """What the official document of `path`'s API says is wrong with one exchange ([] when it fits, or
    when `path` is no CAMARA API)."""
    from openapi_core.testing import MockRequest, MockResponse

    prefix = next((p for p in DOCUMENTS if path.startswith(p)), None)
    if prefix is None:
        return []
    api = _api(DOCUMENTS[prefix])
    body = None if sent is None or method in ("GET", "DELETE") else json.dumps(sent)
    req = MockRequest(HOST, method.lower(), path, data=body, content_type="application/json",
                      headers={"Authorization": "Bearer token", "x-correlator": "spec-check"})  # fmt: skip
    resp = MockResponse(data=b"" if answer is None else json.dumps(answer).encode(), status_code=status,
                        content_type="application/json" if answer is not None else None)  # fmt: skip
    found = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # openapi-core cannot check openIdConnect security
        if request:
            result = api.unmarshal_request(req)
            found += [f"request: {_why(e)}" for e in result.errors if not _security(e) and not _known(e)]
        result = api.unmarshal_response(req, resp)
        found += [f"answer {status}: {_why(e)}" for e in result.errors if not _known(e)]
    return [f"{method} {path}: {p}" for p in found]


def _schema_errors(error: BaseException) -> list[Any]:
    while error is not None:
        if getattr(error, "schema_errors", None):
            return list(error.schema_errors)  # type: ignore[attr-defined]
        error = error.__cause__  # type: ignore[assignment]
    return []


def _known(error: Exception) -> bool:
    """Every schema error of `error` is a known deviation (and there is at least one)."""
    found = _schema_errors(error)
    return bool(found) and all(any(p.search(e.message) for p in KNOWN_DEVIATIONS.values()) for e in found)


def _security(error: Exception) -> bool:
    return "Security" in type(error).__name__


def _why(error: Exception) -> str:
    causes = [str(c) for c in getattr(error, "schema_errors", ())] or [str(error.__cause__ or "")]
    return f"{type(error).__name__}: {error} {'; '.join(causes)}"[:600]
