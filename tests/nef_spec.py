"""Exchanges with a NEF checked against the official 3GPP document (TS 29.122 V18.4.0,
3gpp-as-session-with-qos 1.3.0-alpha.4 and the documents it references), read from ../shared/3gpp with
openapi-core: the request as the document describes it and the answer for its status."""

from __future__ import annotations

import functools
import json
import warnings
from pathlib import Path
from typing import Any

THREEGPP = Path(__file__).resolve().parents[2] / "shared" / "3gpp"
DOCUMENT = "TS29122_AsSessionWithQoS.yaml"
HOST = "http://127.0.0.1:8080"  # the document's {apiRoot}: any root matches


def available() -> str:
    """Why the official document cannot be used ("" when it can)."""
    try:
        import openapi_core  # noqa: F401
    except ModuleNotFoundError:
        return "openapi-core is not installed (pip install -e '.[dev]')"
    if not (THREEGPP / DOCUMENT).is_file():
        return f"the official 3GPP document {DOCUMENT} is absent from {THREEGPP}"
    return ""


@functools.cache
def _api() -> Any:
    from openapi_core import Config, OpenAPI

    # a merge patch (RFC 7396) and a ProblemDetails (RFC 9457) are JSON: openapi-core reads only the
    # media types it knows
    json_too = {"application/merge-patch+json": json.loads, "application/problem+json": json.loads}
    config = Config(extra_media_type_deserializers=json_too)
    return OpenAPI.from_file_path(str(THREEGPP / DOCUMENT), config=config)


def problems(
    method: str,
    path: str,
    sent: Any,
    status: int,
    answer: Any,
    *,
    content_type: str = "application/json",
    headers: dict[str, str] | None = None,
) -> list[str]:
    """What the document says is wrong with one exchange ([] when it fits): the request (path, method,
    body and its content type) and the answer for its status."""
    from openapi_core.testing import MockRequest, MockResponse

    body = None if sent is None else json.dumps(sent)
    request = MockRequest(HOST, method.lower(), path, data=body, content_type=content_type)
    response = MockResponse(data=b"" if answer is None else json.dumps(answer).encode(), status_code=status,
                            content_type=None if answer is None else _answer_type(status),
                            headers=headers or {})  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        found = [f"request: {_why(e)}" for e in _api().unmarshal_request(request).errors]
        found += [f"answer {status}: {_why(e)}" for e in _api().unmarshal_response(request, response).errors]
    return [f"{method} {path}: {p}" for p in found]


def _answer_type(status: int) -> str:
    """An error is a ProblemDetails (RFC 9457, TS 29.122 clause 5.2.6), anything else plain JSON."""
    return "application/problem+json" if status >= 400 else "application/json"


def _why(error: Exception) -> str:
    causes = [str(c) for c in getattr(error, "schema_errors", ())] or [str(error.__cause__ or "")]
    return f"{type(error).__name__}: {error} {'; '.join(causes)}"[:600]


def notification_problems(body: Any) -> list[str]:
    """What the document's UserPlaneNotificationData says is wrong with a notification ([] when it fits):
    the callback's body, checked as its schema (openapi-core checks no callbacks)."""
    from openapi_core.validation.schemas import oas30_write_schema_validators_factory as validators

    spec = _api().spec
    schema = spec / "components" / "schemas" / "UserPlaneNotificationData"
    try:
        validators.create(spec, schema).validate(body)
    except Exception as error:  # openapi-core's InvalidSchemaValue, with each reason
        return [_why(error)]
    return []
