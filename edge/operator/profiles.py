"""CAMARA QoS Profiles (qos-profiles v1.1.0) over the operator client: the profiles the operator offers
this client, which profile_fit.py checks the configured one against."""

from __future__ import annotations

from typing import Any

from dynqos.common.config import CamaraConfig
from dynqos.edge.operator.client import OperatorClient, beside


def profiles_root(cfg: CamaraConfig) -> str:
    """Where the QoS Profiles API is: `profiles_root`, or beside the QoD API."""
    return beside(cfg, cfg.profiles_root, "qos-profiles/v1")


class ProfilesApi:
    """QoS Profiles over an open OperatorClient."""

    def __init__(self, operator: OperatorClient) -> None:
        self.operator = operator
        self.root = profiles_root(operator.cfg)

    async def retrieve(self) -> Any:
        """Every QoS profile the operator offers this client (retrieve-qos-profiles)."""
        return await self.operator.request(
            "POST", "/retrieve-qos-profiles", {}, expect=(200,), root=self.root
        )
