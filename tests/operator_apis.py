"""The QoD API over its own operator client, for the tests that speak to one API alone (the agent and
the fleet planner open one OperatorClient and put every API they use on it)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator

from dynqos.common.config import CamaraConfig
from dynqos.edge.operator.client import OperatorClient
from dynqos.edge.operator.qod import QodApi


@contextlib.asynccontextmanager
async def qod_api(cfg: CamaraConfig) -> AsyncIterator[QodApi]:
    """`async with qod_api(cfg) as client`: QoD calls on `client`, the plumbing's counters on
    `client.operator`."""
    async with OperatorClient(cfg) as operator:
        yield QodApi(operator)
