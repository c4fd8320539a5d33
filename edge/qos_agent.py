"""`dynqos edge qos`: the QoS agent. Drones ask it for priority over zenoh; it makes the network follow.

The drone's supervisor decides alone and switches its zenoh link at once; this process turns the
drone's wish (a QosRequest on `dynqos/<uav>/up/<flow>/qos`) into what the network needs and tells the
drone what it got (a QosGrant on `dynqos/<uav>/down/qos`). It holds the operator credentials; drones
never do. Backends ([qos] backend, docs/qos.md):

- `links`: the network maps the priority port to a dedicated QoS flow by static policy; switching links
  is all there is to do, so priority is AVAILABLE as soon as it is wanted.
- `camara`: one CAMARA Quality-on-Demand session per drone (edge/qod_client.py), created, followed,
  extended and deleted by the rules in edge/qos_grants.py.

With `[qos] policy = "arbiter"` (camara only) a drone gets a session only while the arbiter
(edge/arbiter.py) admits it; every decision is logged, counted and published on
`dynqos/<uav>/down/qos/decision`.

One asyncio task per drone: a slow or failing API call for one drone never holds up another, and
nothing here is on the drone's control path. On start the sessions a crashed agent left behind are
found (retrieve-sessions per configured device) and deleted; on SIGTERM every session it holds is.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import signal
import threading
from typing import Any

from aiohttp import web

from dynqos.common import keys
from dynqos.common.bus import Bus, Priority, Publisher, Received
from dynqos.common.camara import read_secret
from dynqos.common.clock import NS_PER_S, Clock, MonotonicClock, to_ns
from dynqos.common.config import Config
from dynqos.common.errors import ConfigError
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import QosDecision, QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.common.queues import BoundedQueue
from dynqos.edge.arbiter import Action, Arbiter, Decision, Need
from dynqos.edge.qod_client import QodClient, QodError, SessionInfo
from dynqos.edge.qos_grants import DroneGrant, Op, QodStatus, Session
from dynqos.edge.service import Service

log = logging.getLogger(__name__)

SHUTDOWN_S = 10.0  # deleting every session on SIGTERM ends within this
FORGET_AFTER = 10  # a silent drone with no session is forgotten after this many drone timeouts


def preflight(config: Config) -> None:
    """What the operator settings need, checked before any network is opened: an IP address for the
    application server (the network identifies the flow by address) and a readable client secret."""
    if config.qos.backend != "camara":
        return
    server = config.qos.camara.application_server or config.zenoh.edge_host
    try:
        ipaddress.ip_network(server, strict=False)
    except ValueError:
        raise ConfigError(
            "qos.camara.application_server",
            f"{server!r} is not an IP address: the network identifies the flow by address",
        ) from None
    if config.qos.camara.token_url:
        read_secret(config.qos.camara.client_secret_file)


class QosAgent:
    def __init__(self, config: Config, bus: Bus, clock: Clock | None = None) -> None:
        self.config = config
        self.qos = config.qos
        self.camara = config.qos.camara
        self.bus = bus
        self.clock = clock or MonotonicClock()
        self.service = Service("qos", config.qos.health_interval_s)
        self.requests: BoundedQueue[Received] = BoundedQueue(1024)
        self.stats = bus.subscribe(keys.uplink_all_drones(Stream.QOS), self.requests, expect=(QosRequest,))
        self.drones: dict[str, DroneGrant] = {}
        self.wakes: dict[str, asyncio.Event] = {}
        self.tasks: dict[str, asyncio.Task[None]] = {}
        self.publishers: dict[str, Publisher] = {}
        self.client: QodClient | None = None
        self.port = config.zenoh.priority_port
        self.server = self.camara.application_server or config.zenoh.edge_host
        self.stopping = asyncio.Event()
        self.seq = 0
        self.errors = 0
        self.cleaned = 0
        self._logged: set[tuple[str, int, str]] = set()
        self.arbiter = Arbiter(config.qos.arbiter) if config.qos.policy == "arbiter" else None
        self.needs: dict[str, Need] = {}  # each drone's need, from its latest request
        self.refusals: dict[str, str] = {}  # why the arbiter does not admit a drone
        self.decision_pubs: dict[str, Publisher] = {}
        self.decisions = {action: 0 for action in Action}
        preflight(config)

    # ---- the process --------------------------------------------------------------------------------------

    def run(self, ready: Any = None) -> None:
        asyncio.run(self.main(ready))

    async def main(self, ready: Any = None) -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self.stopping.set)
        forward = threading.Thread(target=self._forward, args=(loop,), name="qos-requests", daemon=True)
        sink: web.AppRunner | None = None
        async with contextlib.AsyncExitStack() as stack:
            if self.qos.backend == "camara":
                self.client = await stack.enter_async_context(QodClient(self.camara))
                await self._clean_leftovers()
                if self.camara.sink_listen:
                    sink = await self._serve_sink()
            forward.start()
            if self.arbiter is not None:
                stack.push_async_callback(
                    _cancel, asyncio.get_running_loop().create_task(self._arbitrate_loop())
                )
            log.info(
                "qos agent: backend %s, policy %s, priority port %d, ready",
                self.qos.backend, self.qos.policy, self.port,
            )  # fmt: skip
            if ready is not None:
                ready()
            self.service.write_health("ready")
            while not self.stopping.is_set():
                with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                    await asyncio.wait_for(self.stopping.wait(), self.qos.health_interval_s)
                self.service.maybe_health(self.health)
            self.service.stop.set()
            await self._shut_down()
            if sink is not None:
                await sink.cleanup()
        forward.join(timeout=2)
        log.info("qos agent: stopped; %s", self.health())

    def _forward(self, loop: asyncio.AbstractEventLoop) -> None:
        """zenoh delivers on its own threads into a bounded queue; this hands each request to the loop."""
        while not self.service.stop.is_set():
            item = self.requests.get(0.5)
            if item is not None:
                with contextlib.suppress(RuntimeError):  # the loop has closed: we are stopping
                    loop.call_soon_threadsafe(self._on_request, item)

    def _on_request(self, item: Received) -> None:
        message = item.message
        if not isinstance(message, QosRequest) or self.stopping.is_set():
            return
        uav = message.uav
        grant = self.drones.get(uav)
        if grant is None:
            grant = self.drones[uav] = DroneGrant(uav, self.qos, self.clock.now_ns())
            self.wakes[uav] = asyncio.Event()
            self.publishers[uav] = self.bus.publisher(
                keys.downlink(uav, Downlink.QOS_GRANT), Priority.INTERACTIVE_HIGH
            )
            self.tasks[uav] = asyncio.get_running_loop().create_task(self._drone(uav))
            if self.arbiter is not None:
                grant.admit(False, "waiting for the arbiter")
                self.decision_pubs[uav] = self.bus.publisher(
                    keys.downlink(uav, Downlink.QOS_DECISION), Priority.INTERACTIVE_HIGH
                )
            log.info("qos agent: %s asks for the first time (want=%s)", uav, message.want)
        if message.want != grant.wanted:
            log.info("qos agent: %s %s priority", uav, "wants" if message.want else "no longer wants")
        grant.request(message.want, message.seq, self.clock.now_ns())
        self.needs[uav] = Need(
            risk=message.risk, latency_excess=message.latency_excess, offered_mbps=message.offered_mbps
        )
        self._arbitrate()
        self.wakes[uav].set()

    # ---- the arbiter (policy "arbiter") ---------------------------------------------------------------

    async def _arbitrate_loop(self) -> None:
        """Decide again when a min-hold or turn ends, or a drone goes silent or its hold-down ends."""
        assert self.arbiter is not None
        while not self.stopping.is_set():
            now = self.clock.now_ns()
            wait_s = min(0.5, max(0.001, (self.arbiter.next_change_ns(now) - now) / NS_PER_S))
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(self.stopping.wait(), wait_s)
            if not self.stopping.is_set():
                self._arbitrate()

    def _arbitrate(self) -> None:
        """The arbiter's decisions for the drones' needs now; each drone's grant follows them."""
        if self.arbiter is None:
            return
        now = self.clock.now_ns()
        needs: dict[str, Need] = {}
        for uav, grant in self.drones.items():
            need = self.needs.get(uav, Need())
            if grant.wants(now):
                needs[uav] = need
            elif grant.lingering(now):
                needs[uav] = Need(offered_mbps=need.offered_mbps, lingering=True)
        for decision in self.arbiter.decide(needs, now):
            self._decided(decision, now)
        for uav, grant in self.drones.items():
            admitted = uav in self.arbiter.holders
            reason = self.refusals.get(uav, "waiting for the arbiter")
            if (admitted, reason if not admitted else "") != (grant.admitted, grant.arbiter_reason):
                grant.admit(admitted, f"the arbiter: {reason}" if not admitted else "")
                self.wakes[uav].set()

    def _decided(self, decision: Decision, now: int) -> None:
        assert self.arbiter is not None
        uav, action = decision.uav, decision.action
        self.decisions[action] += 1
        if action in (Action.DENY, Action.REVOKE):
            self.refusals[uav] = decision.reason
        else:
            self.refusals.pop(uav, None)
        level = logging.WARNING if action is Action.REVOKE else logging.INFO
        log.log(level, "qos agent: arbiter %s %s: %s", action.value, uav, decision.reason)
        publisher = self.decision_pubs.get(uav)
        if publisher is None:
            return
        self.seq += 1
        publisher.put(
            QosDecision(
                uav=uav, seq=self.seq, stamp_ns=now, action=action.value, reason=decision.reason[:500],
                risk=decision.need.risk, latency_excess=max(-1.0, min(1.0, decision.need.latency_excess)),
                holders=tuple(sorted(self.arbiter.holders)),
            )
        )  # fmt: skip

    # ---- one drone --------------------------------------------------------------------------------------

    async def _drone(self, uav: str) -> None:
        grant, wake = self.drones[uav], self.wakes[uav]
        told: Grant | None = None
        next_tell = 0
        repeat_ns = to_ns(self.qos.grant_interval_s)
        while not self.stopping.is_set():
            now = self.clock.now_ns()
            op = grant.next_op(now)
            if op is not None:
                try:
                    await self._do(op, grant)
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
                self._tell(grant, state)
                told, next_tell = state, now + repeat_ns
            if grant.silent(now) and grant.session is None:
                if now - grant.heard_ns > FORGET_AFTER * to_ns(self.qos.drone_timeout_s):
                    log.info("qos agent: %s silent; forgotten", uav)
                    self._forget(uav)
                    return
                next_tell = now + to_ns(self.qos.drone_timeout_s)  # nobody listens: no need to repeat
            deadline = min(grant.next_deadline_ns(now), next_tell)
            wake.clear()
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(wake.wait(), max(0.001, (deadline - now) / NS_PER_S))

    def _forget(self, uav: str) -> None:
        self.drones.pop(uav, None)
        self.wakes.pop(uav, None)
        self.tasks.pop(uav, None)
        self.needs.pop(uav, None)
        self.refusals.pop(uav, None)
        for publishers in (self.publishers, self.decision_pubs):
            publisher = publishers.pop(uav, None)
            if publisher is not None:
                publisher.close()

    def _tell(self, grant: DroneGrant, state: Grant) -> None:
        self.seq += 1
        session_id = grant.session.session_id if grant.session else ""
        self.publishers[grant.uav].put(
            QosGrant(
                uav=grant.uav, seq=self.seq, grant=state, backend=self.qos.backend, session_id=session_id,
                reason=grant.why()[:300], answers_seq=grant.request_seq,
            )
        )  # fmt: skip

    async def _do(self, op: Op, grant: DroneGrant) -> None:
        """One API call for one drone, and what its answer means for the drone's grant."""
        client = self.client
        assert client is not None
        device = self.camara.devices.get(grant.uav)
        try:
            if op is Op.RENEW:  # one session per device (409 otherwise): the capped one goes first
                assert grant.session is not None
                old = grant.session.session_id
                with contextlib.suppress(QodError):  # gone already (404) or failing: the create says
                    await client.delete(old)
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
                info = await client.create(self._session_body(device.as_api()))
                log.info("qos agent: %s session %s created (%s)", grant.uav, info.session_id, info.qos_status)
            elif op is Op.DELETE:
                assert grant.session is not None
                await client.delete(grant.session.session_id)
                log.info("qos agent: %s session %s deleted", grant.uav, grant.session.session_id)
                grant.deleted(self.clock.now_ns())
                return
            elif op is Op.EXTEND:
                assert grant.session is not None
                info = await client.extend(grant.session.session_id, self.camara.duration_s)
                if grant.extended(self._session(info), self.clock.now_ns()):
                    log.info(
                        "qos agent: %s session %s is at the operator's maximum duration: replaced "
                        "%.1f s before it ends", grant.uav, info.session_id, self.camara.renew_before_s,
                    )  # fmt: skip
                else:
                    log.info("qos agent: %s session %s extended", grant.uav, info.session_id)
                return
            else:
                assert grant.session is not None
                info = await client.get(grant.session.session_id)
            grant.observed(self._session(info), self.clock.now_ns())
        except QodError as exc:
            await self._failed(op, grant, exc)

    async def _failed(self, op: Op, grant: DroneGrant, exc: QodError) -> None:
        now = self.clock.now_ns()
        self.errors += 1
        reason = f"{op.value}: {exc.status or 'no answer'} {exc.code}: {exc.message}"
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
                grant.failed(op, reason, now)
            else:
                grant.denied(reason, now)

    async def _resolve_conflict(self, grant: DroneGrant) -> None:
        """409 on create: a session for this flow exists (ours from before a restart, or ended and not
        deleted). Reuse it if it is alive; delete it if it has ended, and create afresh."""
        assert self.client is not None
        device = self.camara.devices[grant.uav].as_api()
        try:
            mine = await self._ours(device)
        except QodError as exc:
            grant.failed(Op.CREATE, f"409, then retrieve-sessions: {exc}", self.clock.now_ns())
            return
        if not mine:
            grant.denied("409 CONFLICT, and no session of this device names our port", self.clock.now_ns())
            return
        alive = [s for s in mine if s.qos_status != "UNAVAILABLE"]
        if alive:
            log.info("qos agent: %s reuses session %s (409 on create)", grant.uav, alive[0].session_id)
            grant.observed(self._session(alive[0]), self.clock.now_ns())
            return
        for info in mine:
            with contextlib.suppress(QodError):
                await self.client.delete(info.session_id)
                log.info("qos agent: %s deleted ended session %s (409 on create)", grant.uav, info.session_id)

    async def _ours(self, device: dict[str, Any]) -> list[SessionInfo]:
        """The device's sessions that name our priority port: the ones this agent (or an earlier one) made."""
        assert self.client is not None
        return [s for s in await self.client.retrieve(device) if self.port in s.server_ports()]

    def _session_body(self, device: dict[str, Any]) -> dict[str, Any]:
        address = "ipv6Address" if ":" in self.server else "ipv4Address"
        body: dict[str, Any] = {
            "device": device,
            "applicationServer": {address: self.server},
            "applicationServerPorts": {"ports": [self.port]},
            "qosProfile": self.camara.qos_profile,
            "duration": self.camara.duration_s,
        }
        if self.camara.sink:
            body["sink"] = self.camara.sink
        return body

    def _session(self, info: SessionInfo) -> Session:
        now = self.clock.now_ns()
        expires = None if info.expires_in_s is None else now + round(info.expires_in_s * NS_PER_S)
        return Session(info.session_id, QodStatus(info.qos_status), info.status_info, expires)

    def _once(self, uav: str, status: int, code: str, text: str) -> None:
        """An API error is logged the first time it is seen for a drone; repeats only count."""
        if (uav, status, code) not in self._logged:
            self._logged.add((uav, status, code))
            log.warning("qos agent: %s: %s", uav, text)

    # ---- start and stop -------------------------------------------------------------------------------

    async def _clean_leftovers(self, whose: str = "left by an earlier agent") -> None:
        """Sessions for our priority port that a crashed agent left: found per device, deleted."""
        assert self.client is not None
        for uav, device in self.camara.devices.items():
            try:
                for info in await self._ours(device.as_api()):
                    await self.client.delete(info.session_id)
                    self.cleaned += 1
                    log.warning("qos agent: deleted %s's session %s %s", uav, info.session_id, whose)
            except QodError as exc:
                log.warning("qos agent: cannot check %s for leftover sessions (%s)", uav, exc)

    async def _shut_down(self) -> None:
        """Let each drone's call in flight finish (a create cancelled mid-way would leave a session we
        never heard of), delete every session held, then sweep the devices for any left anyway."""
        for wake in self.wakes.values():
            wake.set()
        tasks = list(self.tasks.values())
        if tasks:
            _, late = await asyncio.wait(tasks, timeout=self.camara.timeout_s + 1)
            for task in late:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        held = [g for g in self.drones.values() if g.session is not None]

        async def release(grant: DroneGrant) -> None:
            assert grant.session is not None
            assert self.client is not None
            try:
                await self.client.delete(grant.session.session_id)
                log.info("qos agent: %s session %s deleted (stopping)", grant.uav, grant.session.session_id)
            except QodError as exc:
                if exc.status != 404:
                    log.error(
                        "qos agent: could not delete %s's session %s: %s",
                        grant.uav,
                        grant.session.session_id,
                        exc,
                    )
            grant.deleted(self.clock.now_ns())

        if held:
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(asyncio.gather(*(release(g) for g in held)), SHUTDOWN_S)
        if self.client is not None:
            with contextlib.suppress(TimeoutError, asyncio.TimeoutError):
                await asyncio.wait_for(self._clean_leftovers("unaccounted for at shutdown"), SHUTDOWN_S)
        for grant in self.drones.values():
            self._tell(grant, Grant.NONE)

    async def _serve_sink(self) -> web.AppRunner:
        """Receive QOS_STATUS_CHANGED notifications: each makes the drone's session be read at once."""
        from urllib.parse import urlsplit

        path = urlsplit(self.camara.sink).path or "/"

        async def notified(request: web.Request) -> web.Response:
            try:
                event = json.loads(await request.read())
                session_id = event["data"]["sessionId"]
            except (ValueError, KeyError, TypeError):
                return web.Response(status=400)
            for grant in self.drones.values():
                if grant.session is not None and grant.session.session_id == session_id:
                    grant.read_now()
                    self.wakes[grant.uav].set()
            return web.Response(status=204)

        app = web.Application(client_max_size=64 * 1024)
        app.router.add_post(path, notified)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        host, _, port = self.camara.sink_listen.rpartition(":")
        await web.TCPSite(runner, host.strip("[]"), int(port)).start()
        log.info("qos agent: notifications on %s (%s)", self.camara.sink_listen, path)
        return runner

    def health(self) -> str:
        sessions = sum(g.session is not None for g in self.drones.values())
        calls = f" api_calls={self.client.calls} retries={self.client.retries}" if self.client else ""
        arbiter = ""
        if self.arbiter is not None:
            d = self.decisions
            arbiter = (
                f" holders={len(self.arbiter.holders)} grants={d[Action.GRANT]} denials={d[Action.DENY]} "
                f"revocations={d[Action.REVOKE]} releases={d[Action.RELEASE]}"
            )
        return (
            f"drones={len(self.drones)} sessions={sessions} errors={self.errors} "
            f"leftovers_cleaned={self.cleaned}{calls}{arbiter} rejected={self.stats.rejected}"
        )


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
