"""A malformed HTTP request (a NUL in a header, a bad request line) is the client's error: aiohttp answers
it 400 and logs it at ERROR with a traceback from its parser. The HTTP servers dynqos runs (the emulated
operator, the QoS agent's sinks) log it as one warning line instead; a traceback is kept for our own bugs."""

from __future__ import annotations

import logging

from aiohttp.http_exceptions import BadHttpMessage


class MalformedRequestLine(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, BadHttpMessage):
            why = " ".join(str(exc.message).split())[:200]
            record.msg, record.args, record.exc_info = "malformed HTTP request answered 400: %s", (why,), None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True


def quiet_malformed_requests() -> None:
    """Install the filter once on aiohttp's server logger (idempotent)."""
    server_log = logging.getLogger("aiohttp.server")
    if not any(isinstance(f, MalformedRequestLine) for f in server_log.filters):
        server_log.addFilter(MalformedRequestLine())
