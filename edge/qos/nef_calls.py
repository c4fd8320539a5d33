"""The QoS agent's calls to a 5G core's NEF (AsSessionWithQoS, edge/operator/nef.py) for one drone at a
time, and what each answer and each notification means for the drone's grant rules (edge/qos/grants.py).

The rules are CAMARA QoD's (docs/qos.md), mapped onto a subscription:

- created, it is REQUESTED until the NEF reports the resources allocated (SUCCESSFUL_RESOURCES_ALLOCATION
  or QOS_GUARANTEED): AVAILABLE. QOS_NOT_GUARANTEED makes it REQUESTED again until QOS_GUARANTEED;
- FAILED_RESOURCES_ALLOCATION and SESSION_TERMINATION end it (UNAVAILABLE): it is deleted and asked for
  again after the back-off; one that ran its `qosDuration` is asked for again at once (as a QoD session's
  DURATION_EXPIRED);
- it has no duration to extend: it lives until deleted, so EXTEND and RENEW are never due;
- a read (GET) returns what was asked, not what was granted: it only finds a subscription gone (404);
- an answer that says the settings are wrong (a 400, 401, 403 or 404 to a create) is not asked again;
- a new active agent adopts the subscription of a drone it hears (and points its notifications at its
  own sink) and deletes the others of its SCS/AS for the priority flow.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Iterable

from dynqos.common.clock import NS_PER_S, Clock
from dynqos.common.config import CamaraConfig
from dynqos.common.config.nef import NefConfig
from dynqos.edge.operator.client import OperatorClient, OperatorError
from dynqos.edge.operator.nef import FlowRule, Monitoring, NefApi, Report, Subscription, SubscriptionRequest
from dynqos.edge.qos.grants import DroneGrant, Op, QodStatus, Session
from dynqos.edge.qos.nef_sink import NefSinkGuard

log = logging.getLogger(__name__)

# What each event says of the subscription: its status, and the statusInfo the grant rules read
EVENT_STATUS = {
    "SUCCESSFUL_RESOURCES_ALLOCATION": (QodStatus.AVAILABLE, ""),
    "QOS_GUARANTEED": (QodStatus.AVAILABLE, ""),
    "QOS_NOT_GUARANTEED": (QodStatus.REQUESTED, "QOS_NOT_GUARANTEED"),
    "FAILED_RESOURCES_ALLOCATION": (QodStatus.UNAVAILABLE, "FAILED_RESOURCES_ALLOCATION"),
    "SESSION_TERMINATION": (QodStatus.UNAVAILABLE, "SESSION_TERMINATION"),
}
EARLY = 256  # events of a subscription whose create has not answered yet, kept until it does
DURATION_SLACK_NS = NS_PER_S  # a termination this close to the end of qosDuration is that duration's


class NefCalls:
    def __init__(
        self,
        operator: OperatorClient,
        nef: NefConfig,
        port: int,
        server: str,
        clock: Clock,
        guard: NefSinkGuard,
        forward: Callable[[str, Report], None] | None = None,
    ) -> None:
        """`port`: the zenoh priority port the flows name; `server`: the edge address the network sees;
        `guard`: the sink whose secret URL each subscription gives the NEF; `forward`: where each QoS
        monitoring report goes, with the drone whose flow it measures (edge/qos/monitoring.py)."""
        self.api = NefApi(operator, nef.api_root, nef.scs_as_id)
        self.nef = nef
        self.port = port
        self.server = server
        self.clock = clock
        self.destination = guard.destination(nef.notification_destination)
        self.errors = 0
        self.cleaned = 0
        self.unknown = 0  # notifications of subscriptions no drone holds
        self.monitoring: dict[str, Report] = {}  # drone id -> its flow's last QoS monitoring report
        self.forward = forward
        self.reports = 0  # QoS monitoring reports of the drones' flows, each forwarded to its drone
        self._created_ns: dict[str, int] = {}
        self._early: collections.OrderedDict[str, tuple[QodStatus, str]] = collections.OrderedDict()
        self._logged: set[tuple[str, int, str]] = set()

    # ---- one drone's calls ------------------------------------------------------------------------------

    async def do(self, op: Op, grant: DroneGrant) -> None:
        """One API call for one drone, and what its answer means for the drone's grant."""
        try:
            if op is Op.CREATE:
                await self._create(grant)
            elif op is Op.DELETE:
                assert grant.session is not None
                await self.api.delete(grant.session.session_id)
                log.info("qos agent: %s subscription %s deleted", grant.uav, grant.session.session_id)
                self._gone(grant)
            else:  # a read: still there (EXTEND and RENEW are never due: a subscription has no end to move)
                assert grant.session is not None
                await self.api.get(grant.session.session_id)
                grant.observed(grant.session, self.clock.now_ns())
        except OperatorError as exc:
            self._failed(op, grant, exc)

    async def _create(self, grant: DroneGrant) -> None:
        ue = self.nef.ues.get(grant.uav)
        if ue is None:
            self._once(grant.uav, 0, "NO_UE", f"no [qos.nef.ues] entry for {grant.uav}")
            grant.denied(f"no UE for {grant.uav} in [qos.nef.ues]", self.clock.now_ns())
            return
        monitoring = Monitoring(self.nef.monitoring_period_s) if self.nef.qos_monitoring else None
        request = SubscriptionRequest(
            ue_ipv4=ue.ipv4,
            ue_ipv6=ue.ipv6,
            gpsi=ue.gpsi,
            flows=(FlowRule(ue.address, self.server, self.port),),
            qos_reference=self.nef.qos_reference,
            alt_qos_references=self.nef.alt_qos_references,
            notification_destination=self.destination,
            qos_duration_s=self.nef.qos_duration_s,
            monitoring=monitoring,
        )
        sub = await self.api.create(request)
        now = self.clock.now_ns()
        self._created_ns[sub.subscription_id] = now
        status, info = self._early.pop(sub.subscription_id, (QodStatus.REQUESTED, ""))
        log.info("qos agent: %s subscription %s created (%s)", grant.uav, sub.subscription_id, status.value)
        grant.observed(Session(sub.subscription_id, status, info), now)

    def _failed(self, op: Op, grant: DroneGrant, exc: OperatorError) -> None:
        now = self.clock.now_ns()
        self.errors += 1
        reason = f"{op.value}: {exc.status or 'no answer'} {exc.code}: {exc.message}"
        retry_after_ns = round((exc.retry_after_s or 0.0) * NS_PER_S)
        if op is Op.CREATE and exc.status in (400, 401, 403, 404):
            why = f"{reason}; fix [qos.nef] ({_setting(exc)}): not asked again until the agent restarts"
            log.error("qos agent: %s: the NEF refused our settings: %s", grant.uav, why)
            grant.refused_settings(why[:300])
        elif exc.status == 404:
            self._gone(grant)  # not there any more (ended and removed, or deleted elsewhere)
        else:
            self._once(grant.uav, exc.status, exc.code, reason)
            grant.failed(op, reason, now, retry_after_ns)

    # ---- what the NEF tells ----------------------------------------------------------------------------

    def notified(self, events: list[Report], grants: Iterable[DroneGrant]) -> list[DroneGrant]:
        """A notification's events applied to the drone holding each subscription (the grants changed);
        events of a subscription being created are kept for its answer, the others counted as unknown."""
        holders = {g.session.session_id: g for g in grants if g.session is not None}
        changed: list[DroneGrant] = []
        for event in events:
            grant = holders.get(event.subscription_id)
            if event.event == "QOS_MONITORING":
                if grant is not None:
                    self.monitoring[grant.uav] = event
                    self.reports += 1
                    if self.forward is not None:
                        self.forward(grant.uav, event)
                continue
            if event.event not in EVENT_STATUS:
                continue
            status, info = self._status(event)
            if grant is None:
                self._keep_early(event.subscription_id, status, info)
                continue
            log.info("qos agent: %s subscription %s: %s", grant.uav, event.subscription_id, event.event)
            grant.observed(Session(event.subscription_id, status, info), self.clock.now_ns())
            changed.append(grant)
        return changed

    def _status(self, event: Report) -> tuple[QodStatus, str]:
        status, info = EVENT_STATUS[event.event]
        created = self._created_ns.get(event.subscription_id)
        duration_ns = self.nef.qos_duration_s * NS_PER_S
        ran_out = (
            created is not None
            and duration_ns > 0
            and self.clock.now_ns() >= created + duration_ns - DURATION_SLACK_NS
        )
        if event.event == "SESSION_TERMINATION" and ran_out:
            info = "DURATION_EXPIRED"  # asked for again at once
        return status, info

    def _keep_early(self, subscription_id: str, status: QodStatus, info: str) -> None:
        self.unknown += 1
        self._early[subscription_id] = (status, info)
        while len(self._early) > EARLY:
            self._early.popitem(last=False)

    # ---- start and stop -------------------------------------------------------------------------------

    async def adopt(self, heard: set[str], whose: str = "left by an earlier agent") -> dict[str, Session]:
        """The SCS/AS's subscriptions for our priority flow, per configured UE: a drone in `heard` keeps
        one (its notifications now come here; taken as AVAILABLE, as the agent that held it had it);
        every other one is deleted."""
        adopted: dict[str, Session] = {}
        try:
            found = await self.api.all()
        except OperatorError as exc:
            log.warning("qos agent: cannot read the NEF's subscriptions (%s)", exc)
            return adopted
        for sub in found:
            uav = self._uav_of(sub)
            if uav is None:
                continue  # not ours: another application's, or another priority port's
            try:
                if uav in heard and uav not in adopted and await self._redirect(sub.subscription_id):
                    adopted[uav] = Session(sub.subscription_id, QodStatus.AVAILABLE)
                    log.info("qos agent: %s subscription %s adopted", uav, sub.subscription_id)
                    continue
                await self.api.delete(sub.subscription_id)
                self.cleaned += 1
                log.warning("qos agent: deleted %s's subscription %s %s", uav, sub.subscription_id, whose)
            except OperatorError as exc:
                log.warning("qos agent: cannot adopt or delete %s's subscription (%s)", uav, exc)
        return adopted

    async def _redirect(self, subscription_id: str) -> bool:
        """Point the subscription's notifications at our sink; False where the NEF has no PATCH (405 or
        501): then it is deleted instead and the drone asks anew, rather than left with the dead agent."""
        try:
            await self.api.modify(subscription_id, {"notificationDestination": self.destination})
        except OperatorError as exc:
            if exc.status not in (405, 501):
                raise
            log.warning(
                "qos agent: the NEF cannot modify a subscription (%s): deleting it instead", exc.status
            )
            return False
        return True

    async def clean_leftovers(self, whose: str = "left by an earlier agent") -> None:
        """Every subscription for our priority flow of a configured UE, deleted."""
        await self.adopt(set(), whose)

    async def release(self, grant: DroneGrant) -> None:
        """Delete the subscription `grant` holds (the agent is stopping); a 404 means it is gone already."""
        assert grant.session is not None
        sid = grant.session.session_id
        try:
            await self.api.delete(sid)
            log.info("qos agent: %s subscription %s deleted (stopping)", grant.uav, sid)
        except OperatorError as exc:
            if exc.status != 404:
                log.error("qos agent: could not delete %s's subscription %s: %s", grant.uav, sid, exc)
        self._gone(grant)

    def _gone(self, grant: DroneGrant) -> None:
        """The drone's subscription is no more: forget when it was made, and tell its grant rules."""
        if grant.session is not None:
            self._created_ns.pop(grant.session.session_id, None)
        grant.deleted(self.clock.now_ns())

    def _uav_of(self, sub: Subscription) -> str | None:
        """The drone whose priority flow `sub` describes (its UE, and our flow's rules), or None."""
        described = {
            d for flow in sub.raw.get("flowInfo") or [] for d in (flow or {}).get("flowDescriptions") or []
        }
        for uav, ue in self.nef.ues.items():
            named = ue.ipv4 or ue.ipv6 or ue.gpsi
            rules = FlowRule(ue.address, self.server, self.port).descriptions()
            if sub.ue == named and all(rule in described for rule in rules):
                return uav
        return None

    def _once(self, uav: str, status: int, code: str, text: str) -> None:
        if (uav, status, code) not in self._logged:
            self._logged.add((uav, status, code))
            log.warning("qos agent: %s: %s", uav, text)


def _setting(exc: OperatorError) -> str:
    """The setting a refused create points at."""
    if exc.status in (401, 403) and exc.code != "QOS_REFERENCE_NOT_AUTHORIZED":
        return "scs_as_id, client_id and its credentials: the NEF does not let this SCS/AS ask"
    if exc.code == "QOS_REFERENCE_NOT_AUTHORIZED" or "qosReference" in exc.message:
        return "qos_reference and alt_qos_references: the core has no such QoS"
    if exc.status == 404:
        return "ues and scs_as_id: the NEF knows no such UE or SCS/AS"
    return "ues, qos_reference and the flow: the NEF refused the request's form"


def client_settings(nef: NefConfig) -> CamaraConfig:
    """The operator client's settings for the NEF (edge/operator/client.py speaks to any of the network's
    APIs): its root, its OAuth2 client credentials, TLS and time-out."""
    return CamaraConfig(
        api_root=nef.api_root,
        token_url=nef.token_url,
        client_id=nef.client_id,
        client_secret_file=nef.client_secret_file,
        scope=nef.scope,
        ca_file=nef.ca_file,
        tls_cert_file=nef.tls_cert_file,
        tls_key_file=nef.tls_key_file,
        timeout_s=nef.timeout_s,
        check_profile=False,
    )
