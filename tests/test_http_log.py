"""A malformed request (a client's error) is one warning line in the servers' logs, not a traceback;
any other error aiohttp logs keeps its traceback."""

from __future__ import annotations

import logging
import sys

from aiohttp.http_exceptions import BadHttpMessage

from dynqos.common.http_log import MalformedRequestLine, quiet_malformed_requests


def record(exc: BaseException) -> logging.LogRecord:
    try:
        raise exc
    except BaseException:
        info = sys.exc_info()
    return logging.LogRecord("aiohttp.server", logging.ERROR, __file__, 1, "Error handling request", (), info)


def test_a_malformed_request_is_one_warning_line_and_other_errors_keep_their_traceback() -> None:
    malformed = record(BadHttpMessage("Invalid header value char:\n  b'X: \\x00'"))
    assert MalformedRequestLine().filter(malformed)
    assert (malformed.levelname, malformed.exc_info) == ("WARNING", None)
    assert "\n" not in malformed.getMessage()
    assert malformed.getMessage().startswith(
        "malformed HTTP request answered 400: Invalid header value char:"
    )
    ours = record(KeyError("a bug of ours"))
    assert MalformedRequestLine().filter(ours)
    assert ours.levelname == "ERROR"
    assert ours.exc_info is not None
    quiet_malformed_requests()
    quiet_malformed_requests()
    assert sum(isinstance(f, MalformedRequestLine) for f in logging.getLogger("aiohttp.server").filters) == 1
