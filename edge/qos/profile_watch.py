"""The operator's QoS profile as the agent last read it: at start, again every `profile_recheck_s`,
and at once when a create is answered as if the profile had changed (422 QOS_PROFILE_NOT_APPLICABLE or
DURATION_OUT_OF_RANGE). An operator may withdraw a profile, make it INACTIVE, or change its duration
range while an agent runs for days; the agent should say so and follow, not refuse every drone until
someone restarts it. The rules of one read are pure (edge/operator/profile_fit.py); this is the shell."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from dynqos.common.config import CamaraConfig
from dynqos.common.errors import ConfigError
from dynqos.edge.operator import profile_fit
from dynqos.edge.operator.client import CREDENTIAL, OperatorClient, OperatorError
from dynqos.edge.operator.profiles import ProfilesApi

log = logging.getLogger(__name__)


def fitted(camara: CamaraConfig, duration_s: int) -> CamaraConfig:
    """The settings with the duration the profile allows; the margins stay inside the shorter session."""
    if duration_s == camara.duration_s:
        return camara
    return replace(
        camara,
        duration_s=duration_s,
        extend_before_s=min(camara.extend_before_s, duration_s / 2),
        renew_before_s=min(camara.renew_before_s, duration_s / 4),
    )


class ProfileWatch:
    """`camara`: the settings to use now (the configured ones, the duration fitted to the profile);
    `withdrawn`: why the profile cannot start a session now ("" = it can)."""

    def __init__(self, operator: OperatorClient, configured: CamaraConfig) -> None:
        self.api = ProfilesApi(operator)
        self.listeners: list[Callable[[], None]] = []  # told of each change, after it is logged
        self._lock = asyncio.Lock()  # one read at a time: several drones may doubt the profile at once
        self.configured = configured
        self.camara = configured
        self.withdrawn = ""
        self.reads = 0
        self.changes = 0
        self._note = ""

    async def start(self) -> CamaraConfig:
        """The first read, before the agent serves: a profile that is not offered or not ACTIVE stops
        the agent (ConfigError naming the setting); an API that does not answer leaves the settings
        unchecked, said once."""
        try:
            answer = await self._answer()
        except OperatorError as exc:  # the token endpoint refused the client: nothing the agent does can work
            raise ConfigError(
                "qos.camara.client_id", f"{exc}: fix client_id and {CREDENTIAL} (or token_url)"
            ) from None
        if answer is None:
            return self.camara
        try:
            fit = profile_fit.fit(answer, self.configured.qos_profile, self.configured.duration_s)
        except profile_fit.ProfileError as exc:
            raise ConfigError("qos.camara.qos_profile", f"{exc}, says {self.api.root}") from None
        log.info("qos agent: %s", fit.note)
        self._note = fit.note
        self.camara = fitted(self.configured, fit.duration_s)
        return self.camara

    async def reread(self) -> bool:
        """Read the profile again; True when what the agent may ask for changed (withdrawn, back, or
        another duration): each change is logged once and its listeners told."""
        async with self._lock:
            changed = await self._reread()
        if changed:
            for listener in self.listeners:
                listener()
        return changed

    async def _reread(self) -> bool:
        answer = await self._answer()
        if answer is None:
            return False
        before = (self.withdrawn, self.camara.duration_s)
        try:
            fit = profile_fit.fit(answer, self.configured.qos_profile, self.configured.duration_s)
        except profile_fit.ProfileError as exc:
            self.withdrawn = f"{exc}, says {self.api.root}; fix [qos.camara] qos_profile"
        else:
            self.withdrawn = ""
            self.camara = fitted(self.configured, fit.duration_s)
            self._note = fit.note
        if (self.withdrawn, self.camara.duration_s) == before:
            return False
        self.changes += 1
        if self.withdrawn:
            log.error(
                "qos agent: no new sessions: %s (read again every %g s)",
                self.withdrawn,
                self.configured.profile_recheck_s,
            )
        else:
            log.warning("qos agent: the operator's profile changed: %s", self._note)
        return True

    async def watch(self) -> None:
        """Read again every `profile_recheck_s`, until cancelled."""
        while True:
            await asyncio.sleep(self.configured.profile_recheck_s)
            await self.reread()

    async def _answer(self) -> Any:
        """The retrieve-qos-profiles answer (checked by profiles.fit), or None when there is none."""
        self.reads += 1
        try:
            return await self.api.retrieve()
        except OperatorError as exc:
            if self.reads == 1 and exc.code == "TOKEN":
                raise
            if self.reads == 1:
                log.warning(
                    "qos agent: the QoS Profiles API at %s did not answer (%s): profile %s and duration "
                    "%d s are not checked",
                    self.api.root,
                    exc,
                    self.configured.qos_profile,
                    self.configured.duration_s,
                )
            else:
                log.info("qos agent: the QoS Profiles API did not answer (%s); settings kept", exc)
            return None
