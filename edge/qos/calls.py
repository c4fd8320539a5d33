"""The QoS agent's calls to the operator's CAMARA Quality-on-Demand API for one drone at a time, and
what each answer means for that drone's grant rules (edge/qos/grants.py): the agent's task asks the rules
which call is due, this makes it and reports the outcome back."""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import time
from collections.abc import Iterator
from typing import Any

from dynqos.common.camara import load_private_key, read_headers, read_secret, tls_context
from dynqos.common.clock import NS_PER_S, Clock
from dynqos.common.config import CamaraConfig, Config
from dynqos.common.errors import ConfigError
from dynqos.edge.operator.client import CREDENTIAL, SUBJECT, OperatorClient, OperatorError
from dynqos.edge.operator.qod import QodApi, SessionInfo
from dynqos.edge.qos.grants import DroneGrant, Op, QodStatus, Session
from dynqos.edge.qos.profile_watch import ProfileWatch
from dynqos.edge.qos.sink import SinkGuard

log = logging.getLogger(__name__)


# Answers that say the agent's own settings are wrong, not the network's state: asking again cannot help.
# CAMARA error codes (quality-on-demand v1.1.0, CAMARA Commonalities) and the setting each one points at.
SETTINGS_AT_FAULT = {
    "UNNECESSARY_IDENTIFIER": "[qos.camara.devices] (the access token already names the device)",
    "UNSUPPORTED_IDENTIFIER": "[qos.camara.devices] (an identifier type this operator does not take)",
    "MISSING_IDENTIFIER": "[qos.camara.devices] (the operator cannot tell which device)",
    "IDENTIFIER_NOT_FOUND": "[qos.camara.devices] (the operator does not know this device)",
    "QUALITY_ON_DEMAND.DURATION_OUT_OF_RANGE": "[qos.camara] duration_s (outside the profile's range)",
    "DURATION_OUT_OF_RANGE": "[qos.camara] duration_s (outside the profile's range)",
    "QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE": "[qos.camara] qos_profile (not offered for this device)",
    "PERMISSION_DENIED": "[qos.camara] client_id and its scopes (the token does not allow this call)",
    "INVALID_TOKEN_CONTEXT": "[qos.camara] the authentication mode (the token does not fit the request)",
    "TOKEN": f"[qos.camara] client_id and {CREDENTIAL} (the token endpoint refused them)",
    # a create the operator cannot read: the same body again cannot help (a version it does not serve)
    "INVALID_ARGUMENT": "[qos.camara] api_version, application_server and [qos.camara.devices] (the "
    "operator refused the request's form)",
}


# A create refused with one of these may mean the operator changed the profile since it was read.
PROFILE_CHANGED = {
    "QUALITY_ON_DEMAND.QOS_PROFILE_NOT_APPLICABLE",
    "QUALITY_ON_DEMAND.DURATION_OUT_OF_RANGE",
    "DURATION_OUT_OF_RANGE",
}


def settings_at_fault(exc: OperatorError) -> str | None:
    """The setting an error points at when it is the agent's configuration, not the network (None)."""
    if exc.code in SETTINGS_AT_FAULT:
        return SETTINGS_AT_FAULT[exc.code]
    if exc.status in (401, 403):
        return f"[qos.camara] client_id, {CREDENTIAL} and token_url (the operator refuses them)"
    return None


class OperatorCalls:
    def __init__(
        self,
        operator: OperatorClient,
        camara: CamaraConfig,
        port: int,
        server: str,
        clock: Clock,
        sink_guard: SinkGuard | None = None,
        profile: ProfileWatch | None = None,
    ) -> None:
        """`port`: the zenoh priority port the sessions name; `server`: the edge address the network sees;
        `sink_guard`: the credential each session gives the operator for its notifications; `profile`:
        the operator's profile as last read (None: not checked)."""
        self.qod = QodApi(operator)  # its sessions, over the agent's one operator client
        self.sink_guard = sink_guard
        self.camara = camara
        self.port = port
        self.server = server
        self.clock = clock
        self.profile = profile
        self.errors = 0
        self.cleaned = 0
        self._logged: set[tuple[str, int, str]] = set()

    async def do(self, op: Op, grant: DroneGrant) -> None:
        """One API call for one drone, and what its answer means for the drone's grant."""
        with self.as_drone(grant.uav):
            await self._do(op, grant)

    @contextlib.contextmanager
    def as_drone(self, uav: str) -> Iterator[None]:
        """The calls inside are this drone's: with `three_legged`, made with its own token."""
        device = self.camara.devices.get(uav)
        token = SUBJECT.set(f"tel:{device.phoneNumber}" if self.camara.three_legged and device else "")
        try:
            yield
        finally:
            SUBJECT.reset(token)

    async def _do(self, op: Op, grant: DroneGrant) -> None:
        qod = self.qod
        device = self.camara.devices.get(grant.uav)
        asked_s = self.camara.duration_s  # what a create asks for: the profile may change meanwhile
        try:
            if op is Op.RENEW:  # one session per device (409 otherwise): the capped one goes first
                assert grant.session is not None
                old = grant.session.session_id
                with contextlib.suppress(OperatorError):  # gone already (404) or failing: the create says
                    await qod.delete(old)
                grant.deleted(self.clock.now_ns())
                log.info("qos agent: %s session %s deleted at its maximum duration; renewing", grant.uav, old)
                op = Op.CREATE
            if op is Op.CREATE:
                if device is None:
                    self._once(grant.uav, 0, "NO_DEVICE", f"no [qos.camara.devices] entry for {grant.uav}")
                    grant.denied(
                        f"no device identity for {grant.uav} in [qos.camara.devices]", self.clock.now_ns()
                    )
                    return
                info = await qod.create(self._session_body(device.as_api()))
                log.info("qos agent: %s session %s created (%s)", grant.uav, info.session_id, info.qos_status)
            elif op is Op.DELETE:
                assert grant.session is not None
                await qod.delete(grant.session.session_id)
                log.info("qos agent: %s session %s deleted", grant.uav, grant.session.session_id)
                grant.deleted(self.clock.now_ns())
                return
            elif op is Op.EXTEND:
                assert grant.session is not None
                info = await qod.extend(grant.session.session_id, self.camara.duration_s)
                if grant.extended(self.session(info), self.clock.now_ns()):
                    log.info(
                        "qos agent: %s session %s is at the operator's maximum duration: replaced "
                        "%.1f s before it ends",
                        grant.uav,
                        info.session_id,
                        self.camara.renew_before_s,
                    )
                else:
                    log.info("qos agent: %s session %s extended", grant.uav, info.session_id)
                return
            else:
                assert grant.session is not None
                info = await qod.get(grant.session.session_id)
            grant.observed(self.session(info), self.clock.now_ns())
        except OperatorError as exc:
            await self._failed(op, grant, exc, asked_s)

    async def _failed(self, op: Op, grant: DroneGrant, exc: OperatorError, asked_s: int = 0) -> None:
        now = self.clock.now_ns()
        self.errors += 1
        reason = f"{op.value}: {exc.status or 'no answer'} {exc.code}: {exc.message}"
        if exc.correlator:
            reason += f" (x-correlator {exc.correlator})"
        setting = settings_at_fault(exc)
        doubted = exc.code in PROFILE_CHANGED and op is Op.CREATE
        if doubted and await self._profile_changed(grant, reason, asked_s):
            return
        if setting is not None and op is Op.CREATE:
            why = f"{reason}; fix {setting}: not asked again until the agent restarts"
            log.error("qos agent: %s: the operator refused our settings: %s", grant.uav, why)
            grant.refused_settings(why[:300])
            return
        retry_after_ns = round((exc.retry_after_s or 0.0) * NS_PER_S)
        if exc.status == 404 and op is not Op.CREATE:
            grant.deleted(now)  # not there any more (expired and removed, or deleted elsewhere)
        elif exc.status == 409 and op is Op.CREATE:
            await self._resolve_conflict(grant)
        elif exc.status == 409 and op is Op.EXTEND:
            grant.failed(op, reason, now)
            grant.read_now()  # the session is no longer AVAILABLE: read what it is
        else:
            self._once(grant.uav, exc.status, exc.code, reason)
            if exc.transient or op is not Op.CREATE:
                grant.failed(op, reason, now, retry_after_ns)
            else:
                grant.denied(reason, now, retry_after_ns)

    async def _profile_changed(self, grant: DroneGrant, reason: str, asked_s: int) -> bool:
        """A create (asking for `asked_s`) refused as if the profile had changed: read it again. True when
        it had (the watch's listener moves every drone to the new settings: this one asks again at once,
        or waits for the profile to be ACTIVE again), False when it had not (this drone's settings)."""
        if self.profile is None:
            return False
        await self.profile.reread()
        if not self.profile.withdrawn and self.profile.camara.duration_s == asked_s:
            return False
        log.warning("qos agent: %s: %s; the profile had changed", grant.uav, reason)
        return True

    async def _resolve_conflict(self, grant: DroneGrant) -> None:
        """409 on create: a session for this flow exists (ours from before a restart, or ended and not
        deleted). Reuse it if it is alive; delete it if it has ended, and create afresh."""
        device = self.camara.devices[grant.uav].as_api()
        try:
            with self.as_drone(grant.uav):
                mine = await self.ours(device)
        except OperatorError as exc:
            grant.failed(Op.CREATE, f"409, then retrieve-sessions: {exc}", self.clock.now_ns())
            return
        if not mine:
            grant.denied("409 CONFLICT, and no session of this device names our port", self.clock.now_ns())
            return
        alive = [s for s in mine if s.qos_status != "UNAVAILABLE"]
        if alive:
            log.info("qos agent: %s reuses session %s (409 on create)", grant.uav, alive[0].session_id)
            grant.observed(self.session(alive[0]), self.clock.now_ns())
            return
        for info in mine:
            with contextlib.suppress(OperatorError), self.as_drone(grant.uav):
                await self.qod.delete(info.session_id)
                log.info("qos agent: %s deleted ended session %s (409 on create)", grant.uav, info.session_id)

    async def ours(self, device: dict[str, Any]) -> list[SessionInfo]:
        """The device's sessions that name our priority port: the ones this agent (or an earlier one) made."""
        named = None if self.camara.three_legged else device  # the drone's token names it already
        return [s for s in await self.qod.retrieve(named) if self.port in s.server_ports()]

    def _session_body(self, device: dict[str, Any]) -> dict[str, Any]:
        listed = self.camara.application_server_addresses  # 1.2.0: the server by its addresses
        address = "ipv6Address" if ":" in self.server else "ipv4Address"
        server = {"ipAddresses": list(listed)} if listed else {address: self.server}
        body: dict[str, Any] = {
            **({} if self.camara.three_legged else {"device": device}),  # three-legged: the token names it
            "applicationServer": server,
            "applicationServerPorts": {"ports": [self.port]},
            "qosProfile": self.camara.qos_profile,
            "duration": self.camara.duration_s,
        }
        if self.camara.sink:
            body["sink"] = self.camara.sink
            if self.sink_guard is not None:
                body["sinkCredential"] = self.sink_guard.credential(self.camara.duration_s, time.time())
        return body

    def session(self, info: SessionInfo) -> Session:
        now = self.clock.now_ns()
        expires = None if info.expires_in_s is None else now + round(info.expires_in_s * NS_PER_S)
        return Session(info.session_id, QodStatus(info.qos_status), info.status_info, expires)

    def _once(self, uav: str, status: int, code: str, text: str) -> None:
        """An API error is logged the first time it is seen for a drone; repeats only count."""
        if (uav, status, code) not in self._logged:
            self._logged.add((uav, status, code))
            log.warning("qos agent: %s: %s", uav, text)

    # ---- start and stop -------------------------------------------------------------------------------

    async def adopt(self, heard: set[str], whose: str = "left by an earlier agent") -> dict[str, Session]:
        """The sessions for our priority port the operator holds, per configured device: a drone in
        `heard` keeps its live one (returned, to be followed as if this agent had made it: an agent that
        takes over creates no duplicate); every other one is deleted (an ended one, a second one, or a
        drone nobody hears: left by a crashed agent)."""
        adopted: dict[str, Session] = {}
        for uav, device in self.camara.devices.items():
            try:
                with self.as_drone(uav):
                    found = await self.ours(device.as_api())
                for info in found:
                    if uav in heard and uav not in adopted and info.qos_status != "UNAVAILABLE":
                        adopted[uav] = self.session(info)
                        log.info(
                            "qos agent: %s session %s adopted (%s)", uav, info.session_id, info.qos_status
                        )
                        continue
                    with self.as_drone(uav):
                        await self.qod.delete(info.session_id)
                    self.cleaned += 1
                    log.warning("qos agent: deleted %s's session %s %s", uav, info.session_id, whose)
            except OperatorError as exc:
                log.warning("qos agent: cannot check %s for sessions (%s)", uav, exc)
        return adopted

    async def clean_leftovers(self, whose: str = "left by an earlier agent") -> None:
        """Every session for our priority port, found per device, deleted."""
        await self.adopt(set(), whose)

    async def release(self, grant: DroneGrant) -> None:
        """Delete the session `grant` holds (the agent is stopping); a 404 means it is gone already."""
        assert grant.session is not None
        session_id = grant.session.session_id
        try:
            with self.as_drone(grant.uav):
                await self.qod.delete(session_id)
            log.info("qos agent: %s session %s deleted (stopping)", grant.uav, session_id)
        except OperatorError as exc:
            if exc.status != 404:
                log.error("qos agent: could not delete %s's session %s: %s", grant.uav, session_id, exc)
        grant.deleted(self.clock.now_ns())


def preflight(config: Config) -> None:
    """What the operator (or NEF) settings need, checked before any network is opened: an IP address for
    the application server (the network identifies the flow by address; a 1.2.0 address list is checked
    with the config) and credential files that load (each error names its key)."""
    camara = config.qos.camara
    if config.qos.backend == "nef":
        nef = config.qos.nef
        _server_address(camara.application_server or config.zenoh.edge_host, "qos.camara.application_server")
        tls_context(nef.ca_file, nef.tls_cert_file, nef.tls_key_file)
        if nef.token_url:
            read_secret(nef.client_secret_file)
        return
    if config.qos.backend != "camara":
        return
    if not camara.application_server_addresses:
        _server_address(camara.application_server or config.zenoh.edge_host, "qos.camara.application_server")
    read_headers(camara.headers_file)
    tls_context(camara.ca_file, camara.tls_cert_file, camara.tls_key_file)
    if camara.token_url:
        read_secret(camara.client_secret_file)
        if camara.client_key_file:
            load_private_key(camara.client_key_file)


def _server_address(server: str, key: str) -> None:
    try:
        ipaddress.ip_network(server, strict=False)
    except ValueError:
        raise ConfigError(
            key, f"{server!r} is not an IP address: the network identifies the flow by address"
        ) from None
