"""The emulated operator's OAuth2 token endpoint and the check of each CAMARA call's credentials.

Tokens: client credentials, the client authenticated by its secret or a client assertion
(private_key_jwt, RFC 7523); or the JWT-bearer grant for one device (three-legged: the assertion's
`sub` is the device's `tel:` login hint). A token carries the scopes asked (all when none is asked);
each call needs its scope (common/camara.py). Or, as aggregators do, fixed API-key headers.
"""

from __future__ import annotations

import collections
import logging
import secrets
import time
from collections.abc import Callable
from typing import Any

from aiohttp import web

from dynqos.common.camara import JWT_BEARER, JWT_BEARER_GRANT, SCOPES, scope_for, signing_algorithm
from dynqos.sim.network.control_http import Reply
from dynqos.sim.network.operator import error

log = logging.getLogger(__name__)

MAX_ASSERTION_LIFETIME_S = 600  # a client assertion valid longer than this is refused
SEEN_ASSERTIONS = 4096  # jti values remembered against replays


class TokenEndpoint:
    def __init__(
        self,
        ttl_s: float,
        client_id: str = "",
        secret: str = "",
        *,
        client_key: Any = None,
        api_headers: dict[str, str] | None = None,
        device_of_phone: Callable[[str], str] = lambda phone: "",
    ) -> None:
        """`secret`: the client secret it takes; `client_key`: the client's registered public key, for
        private_key_jwt assertions (either or both); `api_headers`: with these on a call, no token is
        needed; `device_of_phone`: the drone a phone number names ("" for none)."""
        self.ttl_s = ttl_s
        self.client_id = client_id
        self.secret = secret
        self.client_key = client_key
        self.api_headers = dict(api_headers or {})
        self.device_of_phone = device_of_phone
        # token -> expiry (monotonic), scopes, the drone a three-legged token names ("": two-legged)
        self.tokens: dict[str, tuple[float, frozenset[str], str]] = {}
        self.assertions: collections.OrderedDict[str, None] = collections.OrderedDict()  # jti seen
        self.tokens_issued = 0
        self.tokens_refused = 0  # a client that keeps asking with refused credentials shows here

    def routes(self) -> list[web.RouteDef]:
        return [web.post("/oauth2/token", self.token), web.delete("/oauth2/tokens", self.revoke)]

    def authorise(self, request: web.Request, prefix: str) -> None:
        """The call's credentials, or Reply with the 401/403; a three-legged token's drone goes into the
        request as its `subject`."""
        if self.api_headers:  # an aggregator's fixed API-key headers instead of OAuth2
            if all(
                secrets.compare_digest(request.headers.get(k, ""), v) for k, v in self.api_headers.items()
            ):
                return
            raise Reply(
                error(401, "UNAUTHENTICATED", "request not authenticated: the API key is missing or wrong")
            )
        header = request.headers.get("Authorization", "")
        token = header.removeprefix("Bearer ").strip() if header.startswith("Bearer ") else ""
        expiry, scopes, subject = self.tokens.get(token, (0.0, frozenset(), ""))
        if time.monotonic() >= expiry:
            self.tokens.pop(token, None)
            raise Reply(error(401, "UNAUTHENTICATED", "request not authenticated: a valid token is required"))
        needed = scope_for(request.method, request.path.removeprefix(prefix))
        if needed and needed not in scopes:
            raise Reply(error(403, "PERMISSION_DENIED", f"the token lacks the scope {needed}"))
        request["subject"] = subject

    async def token(self, request: web.Request) -> web.Response:
        answer = await self._token(request)
        if answer.status == 200:
            self.tokens_issued += 1
        else:
            self.tokens_refused += 1
        return answer

    async def _token(self, request: web.Request) -> web.Response:
        form = await request.post()
        grant = form.get("grant_type")
        subject = ""
        if grant == JWT_BEARER_GRANT:
            claims = self._verified(str(form.get("assertion", "")))
            subject = self._device_of_hint(str(claims.get("sub", ""))) if claims else ""
            if not subject:
                return web.json_response({"error": "invalid_grant"}, status=400)
        elif grant != "client_credentials":
            return web.json_response({"error": "unsupported_grant_type"}, status=400)
        elif not self._client_authenticated(form):
            return web.json_response({"error": "invalid_client"}, status=401)
        asked = frozenset(str(form.get("scope", "")).split()) or frozenset(SCOPES.values())
        if not asked <= frozenset(SCOPES.values()):
            unknown = " ".join(sorted(asked - frozenset(SCOPES.values())))
            return web.json_response({"error": "invalid_scope", "error_description": unknown}, status=400)
        token = secrets.token_urlsafe(24)
        now = time.monotonic()
        self.tokens = {t: v for t, v in self.tokens.items() if v[0] > now}  # bounded: live ones only
        self.tokens[token] = (now + self.ttl_s, asked, subject)
        scope = " ".join(sorted(asked))
        return web.json_response(
            {"access_token": token, "token_type": "Bearer", "expires_in": self.ttl_s, "scope": scope}
        )

    def _client_authenticated(self, form: Any) -> bool:
        if not self.client_id or form.get("client_id", self.client_id) != self.client_id:
            return False
        if "client_assertion" in form:
            if form.get("client_assertion_type") != JWT_BEARER:
                return False
            claims = self._verified(str(form["client_assertion"]))
            return claims is not None and claims["sub"] == self.client_id
        return bool(self.secret) and secrets.compare_digest(str(form.get("client_secret", "")), self.secret)

    def _device_of_hint(self, hint: str) -> str:
        """The drone whose phone number a `tel:` login hint names ("" when none)."""
        phone = hint.removeprefix("tel:") if hint.startswith("tel:") else ""
        return self.device_of_phone(phone) if phone else ""

    def _verified(self, assertion: str) -> dict[str, Any] | None:
        """RFC 7523's checks of an assertion: signed by the registered key, issued by the client, for this
        token endpoint (any host, its path), at most MAX_ASSERTION_LIFETIME_S long, its `jti` never used
        before. Its claims, or None."""
        if self.client_key is None:
            return None
        import jwt

        try:
            claims: dict[str, Any] = jwt.decode(
                assertion,
                self.client_key,
                algorithms=[signing_algorithm(self.client_key)],
                issuer=self.client_id,
                options={"require": ["exp", "iat", "jti", "aud", "sub"], "verify_aud": False},
            )
        except jwt.PyJWTError as exc:
            log.info("qod: assertion refused: %s", exc)
            return None
        audience = claims["aud"] if isinstance(claims["aud"], list) else [claims["aud"]]
        if not any(str(a).endswith("/oauth2/token") for a in audience):
            return None
        if claims["exp"] - claims["iat"] > MAX_ASSERTION_LIFETIME_S or claims["jti"] in self.assertions:
            return None
        self.assertions[str(claims["jti"])] = None
        while len(self.assertions) > SEEN_ASSERTIONS:
            self.assertions.popitem(last=False)
        return claims

    async def revoke(self, request: web.Request) -> web.Response:
        count = len(self.tokens)
        self.tokens.clear()
        return web.json_response({"revoked": count})
