"""`dynqos edge qos`: the QoS agent. Drones ask it for priority over zenoh; it makes the network follow.

The drone's supervisor decides alone and switches its zenoh link at once; this process turns the
drone's wish (a QosRequest on `dynqos/<uav>/up/<flow>/qos`) into what the network needs and tells the
drone what it got (a QosGrant on `dynqos/<uav>/down/qos`). It holds the operator credentials; drones
never do. Backends ([qos] backend, docs/qos.md):

- `links`: the network maps the priority port to a dedicated QoS flow by static policy; switching links
  is all there is to do, so priority is AVAILABLE as soon as it is wanted.
- `camara`: one CAMARA Quality-on-Demand session per drone (edge/operator/qod.py), created, followed,
  extended and deleted by the rules in edge/qos/grants.py.
- `nef`: one AsSessionWithQoS subscription per drone at a 5G core's NEF (edge/operator/nef.py), by the
  same rules as they map onto it (edge/qos/nef_calls.py); its state comes with the NEF's notifications.

With `[qos] policy = "arbiter"` (camara only) a drone gets a session only while the arbiter
(edge/qos/arbiter.py) admits it; every decision is logged, counted and published on
`dynqos/<uav>/down/qos/decision`.

One asyncio task per drone: a slow or failing API call for one drone never holds up another, and
nothing here is on the drone's control path. Several agents may run: one is active and holds the
sessions, the others follow the drones' requests and stand by (edge/qos/leadership.py). An agent that
becomes active asks the operator for each configured device's sessions (retrieve-sessions): it adopts
the session of a drone it has heard from, and deletes the others (left by a crashed agent). On SIGTERM
the active agent deletes every session it holds.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from dataclasses import replace
from pathlib import Path

from dynqos.common import keys
from dynqos.common.bus import Priority, Received
from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.config import CamaraConfig, Config
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import QosDecision, QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.edge import metrics as edge_metrics
from dynqos.edge.membership import default_replica_id
from dynqos.edge.operator.client import OperatorClient
from dynqos.edge.operator.nef import Report
from dynqos.edge.qos.arbiter import Action, Arbiter, Decision, Need
from dynqos.edge.qos.calls import OperatorCalls, preflight
from dynqos.edge.qos.grants import DroneGrant
from dynqos.edge.qos.health_line import health_line
from dynqos.edge.qos.leadership import AgentRole, Leadership
from dynqos.edge.qos.monitoring import MonitoringForward
from dynqos.edge.qos.nef_calls import NefCalls, client_settings
from dynqos.edge.qos.nef_sink import NefSinkGuard, serve_nef_sink
from dynqos.edge.qos.peers import AgentPeers
from dynqos.edge.qos.profile_watch import ProfileWatch
from dynqos.edge.qos.record import DroneRecord
from dynqos.edge.qos.sink import SinkGuard, serve_sink
from dynqos.edge.runtime import EdgeCore, Ports, Runtime, serve

log = logging.getLogger(__name__)

SHUTDOWN_S = 10.0  # deleting every session on SIGTERM ends within this
SETTLE_S = 0.5  # after start, before an agent takes over: peers starting with it declare their tokens
HANDOVER_S = 2.0  # a stopping active agent waits this long for a standby to take its sessions over
FORGET_AFTER = 10  # a silent drone with no session is forgotten after this many drone timeouts
READY = "qos agent %s: backend %s, policy %s, priority port %d, %s, ready (%d agent(s) live)"


class QosAgent(EdgeCore):
    name = "qos"

    def __init__(self, config: Config, ports: Ports) -> None:
        bus = ports.bus
        self.config = config
        self.qos = config.qos
        self.camara = config.qos.camara
        self.bus = bus
        self.clock = ports.clock
        self.health_interval_s = config.qos.health_interval_s
        self.inbox = ports.inbox
        self.stats = bus.subscribe(keys.uplink_all_drones(Stream.QOS), self.inbox, expect=(QosRequest,))
        self.drones: dict[str, DroneRecord] = {}  # everything kept of a drone, forgotten in one step
        self.client: OperatorClient | None = None
        self.calls: OperatorCalls | NefCalls | None = None  # with backend "camara" or "nef", once open
        self.profile: ProfileWatch | None = None  # the operator's profile as last read (check_profile)
        self.sink_guard = SinkGuard()  # what the operator's notifications must carry
        self.nef_guard = NefSinkGuard()  # ...and the NEF's, with backend "nef"
        self.port = config.zenoh.priority_port
        self.server = self.camara.application_server or config.zenoh.edge_host
        self.stopping = asyncio.Event()  # the runtime's, from `start`
        self._stack = contextlib.AsyncExitStack()  # what `start` opened, closed by `finish`
        self._lead_task: asyncio.Task[None] | None = None
        self.seq = 0
        self.arbiter = Arbiter(config.qos.arbiter) if config.qos.policy == "arbiter" else None
        self.decisions = {action: 0 for action in Action}
        self.leadership = Leadership(
            config.qos.replica_id or default_replica_id(),
            now_ns=self.clock.now_ns(),
            settle_ns=to_ns(SETTLE_S),
        )
        self.peers: AgentPeers | None = None
        self.serving = False  # active, with the sessions it found adopted: drones are served and told
        self.settled = asyncio.Event()  # its first role is decided (it says it is ready only then)
        preflight(config)

    # ---- the process (edge/runtime.py drives it) -------------------------------------------------------

    async def start(self, runtime: Runtime) -> None:
        """Open the operator client (and its profile watch and sink), find the other agents, and return
        once this agent's first role is decided: the runtime says ready then."""
        self.stopping = runtime.stopping
        loop = asyncio.get_running_loop()
        stack = self._stack
        if self.qos.backend == "camara":
            self.client = await stack.enter_async_context(OperatorClient(self.camara))
            if self.camara.check_profile:
                self.profile = ProfileWatch(self.client, self.camara)
                self._use(await self.profile.start())
                self.profile.listeners.append(self._profile_changed)
                stack.push_async_callback(_cancel, loop.create_task(self.profile.watch()))
            self.calls = OperatorCalls(
                self.client, self.camara, self.port, self.server, self.clock, self.sink_guard, self.profile
            )
            if self.camara.sink_listen:
                sink = await serve_sink(
                    self.camara.sink, self.camara.sink_listen, self._notified, self.sink_guard
                )
                stack.push_async_callback(sink.cleanup)
        if self.qos.backend == "nef":
            nef = self.qos.nef
            self.client = await stack.enter_async_context(OperatorClient(client_settings(nef)))
            forward = MonitoringForward(self.bus, self.clock, nef.monitoring_period_s)
            self.calls = NefCalls(
                self.client, nef, self.port, self.server, self.clock, self.nef_guard, forward
            )
            sink = await serve_nef_sink(
                nef.notification_destination, nef.sink_listen, self._nef_notified, self.nef_guard
            )
            stack.push_async_callback(sink.cleanup)
        group = f"site-{self.qos.site}-all" if self.qos.site else "all"  # one active agent per site
        self.peers = AgentPeers(self.bus, group, self.leadership, loop)
        stack.callback(self.peers.close)
        await loop.run_in_executor(None, self.peers.query)
        self._lead_task = lead = loop.create_task(self._lead())
        settled = loop.create_task(self.settled.wait())
        await asyncio.wait({lead, settled}, return_when=asyncio.FIRST_COMPLETED)
        if lead.done():  # it failed before the first role was decided: say why
            settled.cancel()
            lead.result()
        if self.arbiter is not None:
            stack.push_async_callback(_cancel, loop.create_task(self._arbitrate_loop()))
        lead_, q = self.leadership, self.qos
        log.info(READY, lead_.me, q.backend, q.policy, self.port, lead_.role.value, len(lead_.members))

    async def finish(self) -> None:
        """No takeover while stopping; the sessions handed over or deleted; everything opened closed."""
        if self._lead_task is not None:
            await _cancel(self._lead_task)
        await self._shut_down()
        await self._stack.aclose()

    def handle(self, events: list[Received], now_ns: int) -> None:
        """The drones' requests (zenoh's threads put them into the runtime's inbox)."""
        for item in events:
            self._on_request(item)

    def tick(self, now_ns: int) -> float:
        return self.qos.health_interval_s  # its timers are its tasks': the drones', the leader's

    def _use(self, camara: CamaraConfig) -> None:
        """The operator settings fitted to its profile, for the calls and each drone's grant rules."""
        self.camara = camara
        self.qos = replace(self.qos, camara=camara)
        if isinstance(self.calls, OperatorCalls):
            self.calls.camara = camara

    def _profile_changed(self) -> None:
        """The operator's profile changed (edge/qos/profile_watch.py): every drone follows it."""
        assert self.profile is not None
        self._use(self.profile.camara)
        for record in self.drones.values():
            record.grant.retime(self.camara)
            record.grant.profile_withdrawn(self.profile.withdrawn)
            record.wake.set()

    def _on_request(self, item: Received) -> None:
        message = item.message
        if (
            not isinstance(message, QosRequest)
            or self.stopping.is_set()
            or message.site not in ("", self.qos.site)
        ):
            return  # (another site's: a drone on two paths asks each site's agent for its own path)
        uav = message.uav
        record = self.drones.get(uav)
        if record is None:
            record = self.drones[uav] = self._new_record(uav)
            log.info("qos agent: %s asks for the first time (want=%s)", uav, message.want)
        grant = record.grant
        if message.want != grant.wanted:
            log.info("qos agent: %s %s priority", uav, "wants" if message.want else "no longer wants")
        grant.request(message.want, message.seq, self.clock.now_ns())
        record.need = Need(
            risk=message.risk, latency_excess=message.latency_excess, offered_mbps=message.offered_mbps
        )
        if self.serving:
            self._arbitrate()
            record.wake.set()

    def _new_record(self, uav: str) -> DroneRecord:
        downlink = functools.partial(self.bus.publisher, priority=Priority.INTERACTIVE_HIGH)
        record = DroneRecord(
            grant=DroneGrant(uav, self.qos, self.clock.now_ns()),
            publisher=downlink(keys.downlink(uav, Downlink.QOS_GRANT)),
            decisions=downlink(keys.downlink(uav, Downlink.QOS_DECISION)) if self.arbiter else None,
        )
        if self.arbiter is not None:
            record.grant.admit(False, "waiting for the arbiter")
        if self.profile is not None:
            record.grant.profile_withdrawn(self.profile.withdrawn)
        if self.serving:  # a standby only follows the drone's requests
            record.task = asyncio.get_running_loop().create_task(self._drone(record))
        return record

    # ---- the arbiter (policy "arbiter") ---------------------------------------------------------------

    async def _arbitrate_loop(self) -> None:
        """Decide again when a min-hold or turn ends, or a drone goes silent or its hold-down ends."""
        assert self.arbiter is not None
        while not self.stopping.is_set():
            now = self.clock.now_ns()
            wait_s = min(0.5, max(0.001, (self.arbiter.next_change_ns(now) - now) / NS_PER_S))
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(self.stopping.wait(), wait_s)
            if not self.stopping.is_set() and self.serving:
                self._arbitrate()

    def _arbitrate(self) -> None:
        """The arbiter's decisions for the drones' needs now; each drone's grant follows them."""
        if self.arbiter is None:
            return
        now = self.clock.now_ns()
        needs: dict[str, Need] = {}
        for uav, record in self.drones.items():
            if record.grant.wants(now):
                needs[uav] = record.need
            elif record.grant.lingering(now):
                needs[uav] = Need(offered_mbps=record.need.offered_mbps, lingering=True)
        for decision in self.arbiter.decide(needs, now):
            self._decided(decision, now)
        for uav, record in self.drones.items():
            grant = record.grant
            admitted = uav in self.arbiter.holders
            reason = record.refusal or "waiting for the arbiter"
            if (admitted, reason if not admitted else "") != (grant.admitted, grant.arbiter_reason):
                grant.admit(admitted, f"the arbiter: {reason}" if not admitted else "")
                record.wake.set()

    def _decided(self, decision: Decision, now: int) -> None:
        assert self.arbiter is not None
        uav, action = decision.uav, decision.action
        self.decisions[action] += 1
        record = self.drones.get(uav)
        if record is not None:
            record.refusal = decision.reason if action in (Action.DENY, Action.REVOKE) else ""
        level = logging.WARNING if action is Action.REVOKE else logging.INFO
        log.log(level, "qos agent: arbiter %s %s: %s", action.value, uav, decision.reason)
        publisher = record.decisions if record is not None else None
        if publisher is None:
            return
        self.seq += 1
        publisher.put(
            QosDecision(
                uav=uav,
                seq=self.seq,
                stamp_ns=now,
                action=action.value,
                reason=decision.reason[:500],
                risk=decision.need.risk,
                latency_excess=max(-1.0, min(1.0, decision.need.latency_excess)),
                holders=tuple(sorted(self.arbiter.holders)),
            )
        )

    # ---- one drone --------------------------------------------------------------------------------------

    async def _drone(self, record: DroneRecord) -> None:
        grant, wake, uav = record.grant, record.wake, record.grant.uav
        told: Grant | None = None
        next_tell = 0
        repeat_ns = to_ns(self.qos.grant_interval_s)
        while not self.stopping.is_set():
            now = self.clock.now_ns()
            op = grant.next_op(now)
            if op is not None:
                try:
                    assert self.calls is not None  # an op is due only with a backend that asks
                    await self.calls.do(op, grant)
                except Exception as exc:  # one drone's surprise must not end its task
                    log.exception("qos agent: %s: %s failed unexpectedly", uav, op.value)
                    grant.failed(op, f"{op.value}: {type(exc).__name__}: {exc}"[:300], self.clock.now_ns())
                continue
            state = grant.grant(now)
            if state is not told or now >= next_tell:
                if state is not told:
                    log.info(
                        "qos agent: %s grant %s%s",
                        uav,
                        state.value,
                        f" ({grant.why()})" if grant.why() else "",
                    )
                self._tell(record, state)
                told, next_tell = state, now + repeat_ns
            if grant.silent(now) and grant.session is None:
                if self._long_silent(grant.heard_ns, now):
                    log.info("qos agent: %s silent; forgotten", uav)
                    self._forget(uav)
                    return
                next_tell = now + to_ns(self.qos.drone_timeout_s)  # nobody listens: no need to repeat
            deadline = min(grant.next_deadline_ns(now), next_tell)
            wake.clear()
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(wake.wait(), max(0.001, (deadline - now) / NS_PER_S))

    def _long_silent(self, heard_ns: int, now: int) -> bool:
        """A drone not heard for FORGET_AFTER drone timeouts is forgotten (its record closed)."""
        return now - heard_ns > FORGET_AFTER * to_ns(self.qos.drone_timeout_s)

    def _forget(self, uav: str) -> None:
        record = self.drones.pop(uav, None)
        if record is not None:
            record.close()

    def _tell(self, record: DroneRecord, state: Grant) -> None:
        self.seq += 1
        grant = record.grant
        session_id = grant.session.session_id if grant.session else ""
        record.publisher.put(
            QosGrant(
                uav=grant.uav,
                seq=self.seq,
                grant=state,
                backend=self.qos.backend,
                session_id=session_id,
                reason=grant.why()[:300],
                answers_seq=grant.request_seq,
                site=self.qos.site,
            )
        )

    # ---- which agent is active (edge/qos/leadership.py) --------------------------------------------

    async def _lead(self) -> None:
        """Apply the other agents' token changes; take over or stand by when the rules say so."""
        peers, lead = self.peers, self.leadership
        assert peers is not None
        while not self.stopping.is_set():
            peers.apply()
            now = self.clock.now_ns()
            change = lead.decide(now)
            if change is not None and change.role is AgentRole.ACTIVE:
                await self._take_over(change.reason)
            elif change is not None:
                await self._stand_by(change.reason)
            if not self.serving:
                self._prune(now)
            if lead.next_deadline_ns(now) is None:
                self.settled.set()
            deadline = lead.next_deadline_ns(now)
            timeout = 1.0 if deadline is None else max(0.001, (deadline - now) / NS_PER_S)
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(peers.changed.wait(), timeout)

    async def _take_over(self, reason: str) -> None:
        """Become the active agent: hold the active token first (a peer that also took over sees it and
        steps down), adopt the sessions the operator holds for the drones heard from, delete the rest,
        then serve every drone."""
        assert self.peers is not None
        self.peers.claim()
        log.info("qos agent %s: active: %s", self.leadership.me, reason)
        if self.calls is not None:
            now = self.clock.now_ns()
            heard = {uav for uav, record in self.drones.items() if not record.grant.silent(now)}
            found = await self.calls.adopt(heard)
            now = self.clock.now_ns()
            for uav, record in self.drones.items():
                record.grant.handed_over()
                if uav in found:
                    record.grant.observed(found[uav], now)
        self.serving = True
        loop = asyncio.get_running_loop()
        for record in self.drones.values():
            if record.task is None:
                record.task = loop.create_task(self._drone(record))
        self._arbitrate()

    async def _stand_by(self, reason: str) -> None:
        """Another agent is active (and ranks first): stop serving, hand it the sessions (it finds them
        at the operator), and hold no active token."""
        assert self.peers is not None
        log.warning("qos agent %s: standing by: %s", self.leadership.me, reason)
        self.serving = False
        tasks = [r.task for r in self.drones.values() if r.task is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for record in self.drones.values():
            record.task = None
            record.grant.handed_over()
        self.peers.release()

    def _prune(self, now: int) -> None:
        """A standby forgets the drones silent for long (the active agent's tasks do that for it)."""
        gone = [u for u, r in self.drones.items() if self._long_silent(r.grant.heard_ns, now)]
        for uav in gone:
            self._forget(uav)

    async def _shut_down(self) -> None:
        """Let each drone's call in flight finish (a create cancelled mid-way would leave a session we
        never heard of); hand the sessions to a standby if one takes over within HANDOVER_S (a rolling
        update moves them without a gap), else delete every session held, then sweep the devices for
        any left anyway. A standby holds none and deletes nothing: the sessions are the active agent's."""
        if not self.leadership.is_active:
            return
        for record in self.drones.values():
            record.wake.set()
        tasks = [r.task for r in self.drones.values() if r.task is not None]
        if tasks:
            timeout_s = self.qos.nef.timeout_s if self.qos.backend == "nef" else self.camara.timeout_s
            _, late = await asyncio.wait(tasks, timeout=timeout_s + 1)
            for task in late:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        if self.peers is not None and await self.peers.hand_over(self.clock, HANDOVER_S):
            return
        held = [r.grant for r in self.drones.values() if r.grant.session is not None]
        if self.calls is not None:
            calls = self.calls
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.gather(*(calls.release(g) for g in held)), SHUTDOWN_S)
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(calls.clean_leftovers("unaccounted for at shutdown"), SHUTDOWN_S)
        for record in self.drones.values():
            self._tell(record, Grant.NONE)

    def _notified(self, session_id: str) -> None:
        """News of a session at the sink: the drone holding it has it read at once."""
        for record in self.drones.values():
            session = record.grant.session
            if session is not None and session.session_id == session_id:
                record.grant.read_now()
                record.wake.set()

    def _nef_notified(self, events: list[Report]) -> None:
        """The NEF's news at its sink: the drones whose subscriptions it names act on it at once."""
        if isinstance(self.calls, NefCalls):
            for grant in self.calls.notified(events, (r.grant for r in self.drones.values())):
                self.drones[grant.uav].wake.set()

    @property
    def errors(self) -> int:
        return self.calls.errors if self.calls is not None else 0

    @property
    def cleaned(self) -> int:
        return self.calls.cleaned if self.calls is not None else 0

    def health(self) -> str:
        return health_line(self)


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def run(config: Config, *, health_file: Path | None = None) -> int:
    """`dynqos edge qos` until SIGTERM: the operator settings are checked before any network is opened;
    a hung agent's tokens go after `session_lease_s`, so that a standby takes over."""
    preflight(config)
    lease_s = config.qos.session_lease_s
    return serve("qos", config, QosAgent, edge_metrics.qos, health_file=health_file, lease_s=lease_s)
