"""The one client of an operator's network APIs (CAMARA QoD, QoS Profiles, QoS Booking, Predictive
Connectivity): one HTTP session per process, its OAuth2 tokens, retries, correlators and errors. The
per-API modules beside it (qod.py, profiles.py, booking.py, connectivity.py) only say their paths and
the shapes of their answers, and call `OperatorClient.request`.

Every call is bounded by [qos.camara] timeout_s (or its own `timeout_s`); 429 and 5xx are retried with
jittered exponential back-off inside that bound (a Retry-After header, in seconds or as an HTTP-date, is
honoured when it fits; when it does not, the error carries it for the caller to wait that long); a 401
refreshes the OAuth2 token once and retries. Every call carries an `x-correlator` (one per call, the
same across its retries), which the provider echoes and an operator's support asks for; every error
names it. Other errors raise OperatorError with the API's `code` and `message`, and a `kind` a caller
branches on. A token endpoint that fails (5xx, 429, no answer) is a transient error like the API's own;
one that refuses the credentials is a 401. aiohttp, because the QoS agent is an asyncio program and the
emulated cell serves the APIs with the same library.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import email.utils
import json
import logging
import random
import time
import uuid
from typing import Any

import aiohttp

from dynqos.common.camara import (
    JWT_BEARER,
    JWT_BEARER_GRANT,
    load_private_key,
    read_headers,
    read_secret,
    signing_algorithm,
    tls_context,
)
from dynqos.common.config import CamaraConfig

log = logging.getLogger(__name__)

RETRIES = 3  # attempts after the first, for 429 and 5xx, within the call's timeout
BACKOFF_S = 0.1  # first back-off; doubles, with full jitter
# The drone a call is for, with `three_legged`: its login hint, set by the agent around that drone's calls
SUBJECT: contextvars.ContextVar[str] = contextvars.ContextVar("operator_subject", default="")
ASSERTION_LIFETIME_S = 300  # a client assertion is good for this long (and used once)
CREDENTIAL = "its credential (client_secret_file, client_key_file or headers_file)"  # as errors name it
TOKEN_MARGIN_S = 30.0  # a token is refreshed this long (at most a quarter of its life) before it expires


class OperatorError(Exception):
    """An operator API answered with an error (status, CAMARA `code`, `message`), or did not answer
    (status 0)."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        correlator: str = "",
        retry_after_s: float | None = None,
    ) -> None:
        super().__init__(
            f"{status} {code}: {message}" + (f" (x-correlator {correlator})" if correlator else "")
        )
        self.status = status
        self.code = code
        self.message = message
        self.correlator = correlator  # the call's x-correlator: what the operator's support looks up
        self.retry_after_s = retry_after_s  # the operator's Retry-After, when the call could not wait it out

    @property
    def transient(self) -> bool:
        """Worth asking again later: no answer, throttled, or a server error."""
        return self.status in (0, 429) or self.status >= 500

    @property
    def kind(self) -> str:
        """What went wrong, as a caller branches on it: "unreachable" (no answer), "throttled" (429),
        "server" (5xx), "credentials" (401: the token or the client), "forbidden" (403: the scopes or the
        device), "not_found" (404), "conflict" (409), or "refused" (any other 4xx: the request itself)."""
        if self.status == 0:
            return "unreachable"
        if self.status >= 500:
            return "server"
        named = {429: "throttled", 401: "credentials", 403: "forbidden", 404: "not_found", 409: "conflict"}
        return named.get(self.status, "refused")


class OperatorClient:
    """One operator's network APIs. Create with `async with OperatorClient(cfg) as operator`; the
    per-API modules take it (`QodApi(operator)`, `BookingApi(operator)`, ...)."""

    def __init__(self, cfg: CamaraConfig, *, rng: random.Random | None = None) -> None:
        self.cfg = cfg
        self.root = cfg.api_root.rstrip("/")
        self.secret = read_secret(cfg.client_secret_file) if cfg.token_url else ""
        self.fixed_headers = read_headers(cfg.headers_file)
        self.tls = tls_context(cfg.ca_file, cfg.tls_cert_file, cfg.tls_key_file)
        self.key = load_private_key(cfg.client_key_file) if cfg.token_url and cfg.client_key_file else None
        self.rng = rng or random.Random()
        self.http: aiohttp.ClientSession | None = None
        self._tokens: dict[str, tuple[str, float]] = {}  # subject ("": two-legged) -> token, refresh time
        self._token_lock = asyncio.Lock()
        self.calls = 0
        self.retries = 0
        self.token_refreshes = 0

    async def __aenter__(self) -> OperatorClient:
        connector = aiohttp.TCPConnector(ssl=self.tls) if self.tls is not None else None
        self.http = aiohttp.ClientSession(
            timeout=aiohttp.ClientTimeout(total=self.cfg.timeout_s), connector=connector
        )
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self.http is not None:
            await self.http.close()

    async def request(
        self,
        method: str,
        path: str,
        body: dict[str, Any] | None,
        *,
        expect: tuple[int, ...],
        root: str = "",
        timeout_s: float | None = None,
        content_type: str = "application/json",
    ) -> Any:
        """A call to one of the operator's APIs (under `root`; the QoD API's root when empty), with this
        client's token, correlator, retries and time-out (`timeout_s` in its place for this call): the
        answer's JSON, or an OperatorError. `content_type`: the body's (a merge patch's is
        application/merge-patch+json, RFC 7396)."""
        return await self._call(
            method, path, body, expect=expect, root=root, timeout_s=timeout_s, content_type=content_type
        )

    # ---- one call: token, timeout, retries --------------------------------------------------------------

    async def _call(
        self,
        method: str,
        path: str,
        body: dict[str, Any] | None = None,
        *,
        expect: tuple[int, ...],
        root: str = "",
        timeout_s: float | None = None,
        content_type: str = "application/json",
    ) -> Any:
        limit_s = self.cfg.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + limit_s
        correlator = str(uuid.uuid4())
        refreshed = False
        attempt = 0
        sent = None if body is None else (json.dumps(body).encode(), content_type)  # once, for every try
        while True:
            self.calls += 1
            url = (root or self.root) + path
            status, answer, retry_after = await self._once(method, url, sent, deadline, limit_s, correlator)
            if status in expect:
                return answer
            # the token endpoint refused the credential: asking it again now would be refused too
            token_refused = isinstance(answer, dict) and answer.get("code") == "TOKEN"
            if status == 401 and self.cfg.token_url and not refreshed and not token_refused:
                refreshed = True
                self._tokens.pop(SUBJECT.get(), None)  # the API no longer takes it: get a new one, once more
                continue
            error = _error(status, answer, correlator, retry_after)
            if not error.transient or attempt >= RETRIES:
                raise error
            pause = retry_after if retry_after is not None else self.rng.uniform(0, BACKOFF_S * 2**attempt)
            if time.monotonic() + pause >= deadline:
                raise error
            attempt += 1
            self.retries += 1
            log.debug("operator: %s %s: %s; retrying in %.2f s", method, path, error, pause)
            await asyncio.sleep(pause)  # the back-off itself

    async def _once(
        self,
        method: str,
        url: str,
        sent: tuple[bytes, str] | None,
        deadline: float,
        limit_s: float,
        correlator: str,
    ) -> tuple[int, Any, float | None]:
        """One attempt before the call's `deadline` (monotonic); `limit_s`, its time-out, for the message;
        `sent`, the body as sent and its content type (None: no body)."""
        assert self.http is not None, "use `async with OperatorClient(...)`"
        timed_out = {"code": "TIMEOUT", "message": f"no answer within {limit_s:g} s"}
        left = deadline - time.monotonic()
        if left <= 0:
            return 0, timed_out, None
        headers = {**self.fixed_headers, "Accept": "application/json", "x-correlator": correlator}
        data = None
        if sent is not None:
            data, headers["Content-Type"] = sent
        try:
            token = await asyncio.wait_for(self._bearer(), left)
            if token:
                headers["Authorization"] = f"Bearer {token}"
            async with self.http.request(
                method,
                url,
                data=data,
                headers=headers,
                timeout=aiohttp.ClientTimeout(total=max(0.01, deadline - time.monotonic())),
            ) as response:
                answer: Any = None
                if response.content_length != 0 and response.status != 204:
                    with contextlib.suppress(aiohttp.ContentTypeError, ValueError):
                        answer = await response.json(content_type=None)
                return response.status, answer, retry_after_s(response.headers.get("Retry-After"))
        except OperatorError as exc:
            return exc.status, {"code": exc.code, "message": exc.message}, None
        except (TimeoutError, asyncio.TimeoutError):
            return 0, timed_out, None
        except aiohttp.ClientError as exc:
            return 0, {"code": "UNREACHABLE", "message": f"{type(exc).__name__}: {exc}"[:300]}, None

    async def _bearer(self) -> str:
        """The access token, fetched when there is none or it is about to expire: the client's own
        (client credentials), or with `three_legged` the current drone's (SUBJECT, the JWT-bearer grant)."""
        if not self.cfg.token_url:
            return ""
        subject = SUBJECT.get() if self.cfg.three_legged else ""
        async with self._token_lock:
            token, refresh_at = self._tokens.get(subject, ("", 0.0))
            if token and time.monotonic() < refresh_at:
                return token
            assert self.http is not None
            form = self._token_form(subject)
            async with self.http.post(self.cfg.token_url, data=form) as response:
                answer = await response.json(content_type=None) if response.status == 200 else None
                if response.status == 429 or response.status >= 500:  # the endpoint's trouble, not ours
                    raise OperatorError(
                        response.status, "TOKEN_ENDPOINT", f"the token endpoint answered {response.status}"
                    )
                if not isinstance(answer, dict) or not isinstance(answer.get("access_token"), str):
                    raise OperatorError(401, "TOKEN", f"the token endpoint answered {response.status}")
            token = answer["access_token"]
            ttl = float(answer.get("expires_in", 3600))
            # refreshed ahead of its expiry: a call never starts with a token about to lapse
            self._tokens[subject] = (token, time.monotonic() + ttl - min(TOKEN_MARGIN_S, ttl / 4))
            self.token_refreshes += 1
            log.info(
                "operator: new access token%s (expires in %.0f s)", f" for {subject}" if subject else "", ttl
            )
            return str(token)

    def _token_form(self, subject: str = "") -> dict[str, str]:
        """The token request. Client credentials: the secret in the form, or (private_key_jwt, RFC 7523
        section 2.2) a client assertion signed with the key, for this token endpoint, used once (`jti`),
        for 5 minutes. For a `subject` (three-legged, RFC 7523 section 2.1): the JWT-bearer grant, an
        assertion of the same kind whose `sub` is the device's login hint (`tel:+46...`)."""
        scope = {"scope": self.cfg.scope} if self.cfg.scope else {}
        if subject:
            assertion = self._assertion(subject)
            return {
                "grant_type": JWT_BEARER_GRANT,
                "assertion": assertion,
                "client_id": self.cfg.client_id,
            } | scope
        form = {"grant_type": "client_credentials", "client_id": self.cfg.client_id} | scope
        if self.key is None:
            return form | {"client_secret": self.secret}
        return form | {
            "client_assertion_type": JWT_BEARER,
            "client_assertion": self._assertion(self.cfg.client_id),
        }

    def _assertion(self, subject: str) -> str:
        import jwt  # PyJWT: the signing and the claims, as identity servers check them

        assert self.key is not None, "client assertions need [qos.camara] client_key_file"
        now = int(time.time())
        claims = {
            "iss": self.cfg.client_id,
            "sub": subject,
            "aud": self.cfg.token_url,
            "jti": str(uuid.uuid4()),
            "iat": now,
            "exp": now + ASSERTION_LIFETIME_S,
        }
        return str(jwt.encode(claims, self.key, algorithm=signing_algorithm(self.key)))


def beside(cfg: CamaraConfig, explicit: str, api: str) -> str:
    """Where another CAMARA API of the operator is: `explicit`, or beside the QoD API as CAMARA publishes
    them ({apiRoot}/quality-on-demand/v1 and {apiRoot}/<api>, e.g. qos-profiles/v1)."""
    if explicit:
        return explicit.rstrip("/")
    root = cfg.api_root.rstrip("/")
    base, _, _ = root.rpartition("/quality-on-demand/")
    return f"{base or root.rsplit('/', 2)[0]}/{api}"


def _error(status: int, answer: Any, correlator: str, retry_after: float | None) -> OperatorError:
    """CAMARA's ErrorInfo (`code`, `message`) or 3GPP's ProblemDetails (`cause`, `detail`)."""
    code, message = "", "no error body"
    if isinstance(answer, dict):
        code = str(answer.get("code", "") or answer.get("cause", ""))
        message = str(answer.get("message", "") or answer.get("detail", ""))[:300]
    return OperatorError(status, code, message, correlator=correlator, retry_after_s=retry_after)


def retry_after_s(value: str | None, now_unix: float | None = None) -> float | None:
    """A Retry-After header in seconds: delta-seconds, or an HTTP-date (RFC 9110) from now; None when
    absent or unreadable."""
    if value is None:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        at = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if at.tzinfo is None:
        return None  # an HTTP-date is always GMT; one without a zone is not one
    return max(0.0, at.timestamp() - (time.time() if now_unix is None else now_unix))
