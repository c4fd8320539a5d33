"""CAMARA Quality-on-Demand (quality-on-demand v1.1.0, CAMARA release r3.2) over the operator client.

Only the calls dynqos needs: create, get, extend and delete a session, and retrieve a device's sessions
(to clean up after a crashed agent and to resolve a 409). An answer without a SessionInfo's shape is a
502 BAD_RESPONSE: the agent never acts on half an answer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from dynqos.common.camara import QOS_STATUS, ports_named
from dynqos.edge.operator.client import OperatorClient, OperatorError


@dataclass(frozen=True, slots=True)
class SessionInfo:
    """The fields of a CAMARA SessionInfo the agent acts on; `raw` is the whole object."""

    session_id: str
    qos_status: str
    status_info: str
    expires_in_s: float | None  # from expiresAt, on the local wall clock (None when not given)
    raw: dict[str, Any]

    @classmethod
    def parse(cls, body: Any) -> SessionInfo:
        if not isinstance(body, dict) or not isinstance(body.get("sessionId"), str):
            raise OperatorError(502, "BAD_RESPONSE", f"not a SessionInfo: {str(body)[:200]}")
        status = body.get("qosStatus")
        if status not in QOS_STATUS:
            raise OperatorError(502, "BAD_RESPONSE", f"unknown qosStatus {status!r}")
        expires = None
        if isinstance(body.get("expiresAt"), str):
            try:
                at = datetime.fromisoformat(body["expiresAt"].replace("Z", "+00:00"))
                expires = at.timestamp() - time.time()
            except ValueError:
                raise OperatorError(
                    502, "BAD_RESPONSE", f"expiresAt {body['expiresAt']!r} is not RFC 3339"
                ) from None
        return cls(body["sessionId"], status, str(body.get("statusInfo", "")), expires, body)

    def server_ports(self) -> list[int]:
        return sorted(ports_named(self.raw.get("applicationServerPorts")))


class QodApi:
    """QoD sessions over an open OperatorClient, under its `api_root`."""

    def __init__(self, operator: OperatorClient) -> None:
        self.operator = operator

    async def create(self, body: dict[str, Any]) -> SessionInfo:
        return SessionInfo.parse(await self.operator.request("POST", "/sessions", body, expect=(201, 200)))

    async def get(self, session_id: str) -> SessionInfo:
        return SessionInfo.parse(
            await self.operator.request("GET", f"/sessions/{session_id}", None, expect=(200,))
        )

    async def extend(self, session_id: str, seconds: int) -> SessionInfo:
        body = {"requestedAdditionalDuration": seconds}
        path = f"/sessions/{session_id}/extend"
        return SessionInfo.parse(await self.operator.request("POST", path, body, expect=(200,)))

    async def delete(self, session_id: str) -> None:
        await self.operator.request("DELETE", f"/sessions/{session_id}", None, expect=(204, 200))

    async def retrieve(self, device: dict[str, Any] | None) -> list[SessionInfo]:
        """The device's sessions; `device` None when a three-legged token names it."""
        query = {} if device is None else {"device": device}
        body = await self.operator.request("POST", "/retrieve-sessions", query, expect=(200,))
        if not isinstance(body, list):
            raise OperatorError(502, "BAD_RESPONSE", "retrieve-sessions did not answer an array")
        return [SessionInfo.parse(item) for item in body]
