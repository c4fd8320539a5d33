"""The one place that turns config into zenoh sessions, and the thin publish/subscribe seam.

A 5G QoS flow is a zenoh link with a priority range to its own router port (docs/architecture.md):
the drone's session is a *peer* that connects to `tcp/<edge>:7447?prio=4-7` (default flow) and
`tcp/<edge>:7448?prio=1-3#dscp=0xb8` (priority flow), listens on nothing and scouts nothing, so
every byte crosses exactly those two links. Client mode would open only the first endpoint.
`transport/unicast/max_links` must be >= 2 on both ends or the second link silently never opens.
Edge services are clients of the router. Shared memory is off by default: on one host it would
let large payloads bypass the links (and the cell emulator).

Pure code never imports zenoh: it sees the `Bus` and `Publisher` protocols of `common.bus`, which
`ZenohBus` implements here. Subscriber callbacks only decode and hand off to a bounded queue; they
never block.
"""

from __future__ import annotations

import enum
import ipaddress
import json
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from dynqos.common.acl import access_control_policy
from dynqos.common.bus import Bus as Bus
from dynqos.common.bus import Newest, SubscriptionStats, delivery
from dynqos.common.bus import Priority as Priority
from dynqos.common.bus import Publisher as Publisher
from dynqos.common.bus import Received as Received
from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.config import ZenohConfig
from dynqos.common.errors import ConfigError, TransportError
from dynqos.common.messages import Message, decode, encode
from dynqos.common.queues import BoundedQueue

log = logging.getLogger(__name__)


class Role(str, enum.Enum):
    DRONE = "drone"  # peer, connects to both flow ports, listens on nothing
    EDGE = "edge"  # client of the router
    ROUTER = "router"  # listens on both flow ports


DEFAULT_FLOW_PRIORITIES = (4, 7)
PRIORITY_FLOW_PRIORITIES = (1, 3)

_ZENOH_PRIORITY = {
    Priority.REAL_TIME: zenoh.Priority.REAL_TIME,
    Priority.INTERACTIVE_HIGH: zenoh.Priority.INTERACTIVE_HIGH,
    Priority.INTERACTIVE_LOW: zenoh.Priority.INTERACTIVE_LOW,
    Priority.DATA_HIGH: zenoh.Priority.DATA_HIGH,
    Priority.DATA: zenoh.Priority.DATA,
    Priority.DATA_LOW: zenoh.Priority.DATA_LOW,
    Priority.BACKGROUND: zenoh.Priority.BACKGROUND,
}


def _host(host: str) -> str:
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def _scheme(cfg: ZenohConfig) -> str:
    return "tls" if cfg.tls else "tcp"


def default_flow_endpoint(cfg: ZenohConfig, host: str | None = None, port: int | None = None) -> str:
    lo, hi = DEFAULT_FLOW_PRIORITIES
    endpoint = f"{_scheme(cfg)}/{_host(host or cfg.edge_host)}:{port or cfg.default_port}?prio={lo}-{hi}"
    if cfg.bulk_sndbuf_bytes:
        endpoint += f"#so_sndbuf={cfg.bulk_sndbuf_bytes}"
    return endpoint


def priority_flow_endpoint(cfg: ZenohConfig, host: str | None = None, port: int | None = None) -> str:
    lo, hi = PRIORITY_FLOW_PRIORITIES
    endpoint = f"{_scheme(cfg)}/{_host(host or cfg.edge_host)}:{port or cfg.priority_port}?prio={lo}-{hi}"
    return endpoint + f"#dscp={cfg.priority_dscp:#x}"


def router_endpoints(cfg: ZenohConfig) -> list[str]:
    host = _host(cfg.router_listen_host)
    return [f"{_scheme(cfg)}/{host}:{port}" for port in (cfg.default_port, cfg.priority_port)]


def endpoints(
    cfg: ZenohConfig,
    role: Role,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
) -> tuple[list[str], list[str]]:
    """(connect, listen) endpoints for `role`; explicit lists replace those derived from cfg."""
    if connect is None:
        if role is Role.DRONE:
            connect = [default_flow_endpoint(cfg), priority_flow_endpoint(cfg)]
        elif role is Role.EDGE:
            connect = [f"{_scheme(cfg)}/{_host(cfg.edge_host)}:{cfg.default_port}"]
        else:
            connect = list(cfg.router_links)  # the other edge sites' routers
    if listen is None:
        listen = router_endpoints(cfg) if role is Role.ROUTER else []
    return list(connect), list(listen)


def session_settings(
    cfg: ZenohConfig,
    role: Role,
    *,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    check_files: bool = True,
    client: bool = False,
    lease_s: float | None = None,
) -> dict[str, Any]:
    """The zenoh settings for `role`, as `path/to/key: value` (what `dynqos config zenoh` prints).

    `check_files`: fail now, naming the key, if a TLS file is missing (rather than in zenoh's words).
    `client`: a client session with the role's identity. A router forwards nothing between two peers
    (it expects them to reach each other), so the preflight hears its own clock probes on a client.
    `lease_s`: the lease this session announces (zenoh's default 10 s): the router closes it, and
    withdraws its tokens, after that long without a keep-alive from a process that hangs.
    """
    connect, listen = endpoints(cfg, role, connect, listen)
    mode = "client" if client else {Role.DRONE: "peer", Role.EDGE: "client", Role.ROUTER: "router"}[role]
    settings: dict[str, Any] = {
        "mode": mode,
        "connect/endpoints": list(connect),
        "listen/endpoints": list(listen),
        "scouting/multicast/enabled": False,
        "scouting/gossip/enabled": False,
        "transport/unicast/max_links": cfg.max_links,
        "transport/shared_memory/enabled": cfg.shared_memory,
        "connect/timeout_ms": round(cfg.connect_timeout_s * 1000),
        # a router keeps trying another site's router (zenoh retries); anyone else stops, saying why
        "connect/exit_on_failure": role is not Role.ROUTER,
    }
    # zenoh's open waits up to `scouting/delay` (500 ms) for the peers it could scout. With scouting off a
    # router has none: it starts 0.5 s sooner. A drone's peer session keeps the wait (its two links).
    if mode == "router":
        settings["scouting/delay"] = 0
    if lease_s is not None:
        settings["transport/link/tx/lease"] = round(lease_s * 1000)
    if cfg.tls:
        settings.update(_tls_settings(cfg, role, check_files))
    if role is Role.ROUTER:
        policy = router_access_control(cfg)
        if policy is not None:
            settings["access_control"] = policy
    return settings


def router_access_control(cfg: ZenohConfig) -> dict[str, Any] | None:
    """The router's access-control policy, failing closed: TLS without a policy is refused unless
    `acl = "off"` says so, and every setup that lets anyone in is logged as a warning naming the risk."""
    if cfg.tls and cfg.acl_drones:
        return access_control_policy(
            cfg.acl_drones, cfg.acl_ros2_clients, cfg.acl_ros2_domain_id, cfg.acl_ros2_prefix, cfg.acl_tasks
        )
    if cfg.tls and cfg.acl == "on":
        raise ConfigError(
            "zenoh.acl_drones",
            "is empty with tls = true: the router would let every certificate from the CA command every "
            'drone and read all traffic. List the drones, or set zenoh.acl = "off" to run without '
            "access control on purpose",
        )
    if cfg.tls:
        log.warning(
            'router: TLS WITHOUT ACCESS CONTROL (zenoh.acl = "off"): any certificate signed by %s may '
            "publish to and read every drone's keys",
            cfg.tls_ca,
        )
    elif not _loopback(cfg.router_listen_host):
        log.warning(
            "router: PLAIN TCP ON %s WITHOUT AUTHENTICATION: anyone who reaches ports %d/%d can command "
            "every drone and read all traffic; use tls = true with acl_drones outside a trusted network",
            cfg.router_listen_host,
            cfg.default_port,
            cfg.priority_port,
        )
    return None


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a name other than localhost: it may resolve to anything


def nested(settings: dict[str, Any]) -> dict[str, Any]:
    """`{"a/b": 1}` as `{"a": {"b": 1}}`: a config file zenohd reads."""
    tree: dict[str, Any] = {}
    for path, value in settings.items():
        *parents, leaf = path.split("/")
        node = tree
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def session_config(
    cfg: ZenohConfig,
    role: Role,
    *,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    client: bool = False,
    lease_s: float | None = None,
) -> zenoh.Config:
    """A zenoh.Config for `role`; `connect`/`listen` replace the endpoints derived from cfg."""
    zcfg = zenoh.Config()
    settings = session_settings(cfg, role, connect=connect, listen=listen, client=client, lease_s=lease_s)
    for key, value in settings.items():
        zcfg.insert_json5(key, json.dumps(value))
    return zcfg


def _tls_settings(cfg: ZenohConfig, role: Role, check_files: bool) -> dict[str, Any]:
    """Mutual TLS: the router demands a certificate from every session and everyone checks the CA."""
    for name in ("tls_ca", "tls_cert", "tls_key"):
        path = getattr(cfg, name)
        if check_files and not Path(path).is_file():
            raise ConfigError(name, f"{path!r} is not a readable file")
    tls: dict[str, Any] = {"root_ca_certificate": cfg.tls_ca}
    if role is Role.ROUTER:
        tls |= {"listen_certificate": cfg.tls_cert, "listen_private_key": cfg.tls_key, "enable_mtls": True}
    else:
        tls |= {"connect_certificate": cfg.tls_cert, "connect_private_key": cfg.tls_key, "enable_mtls": True}
    return {f"transport/link/tls/{key}": value for key, value in tls.items()}


@dataclass(frozen=True, slots=True)
class LinkInfo:
    src: str
    dst: str
    priorities: tuple[int, int] | None


class ZenohPublisher:
    """A zenoh publisher on one key with a priority fixed at declaration (zenoh's rule)."""

    def __init__(self, inner: zenoh.Publisher, key: str) -> None:
        self._inner = inner
        self.key = key
        self.sent = 0
        self.sent_bytes = 0

    def put(self, message: Message) -> None:
        self.put_bytes(encode(message))

    def put_bytes(self, data: bytes, attachment: bytes | None = None) -> None:
        self._inner.put(data, attachment=attachment)
        self.sent += 1
        self.sent_bytes += len(data)

    def wait_matched(self, timeout_s: float) -> bool:
        """Wait until at least one subscriber matches this key (False on timeout).

        Zenoh drops a put that no subscriber matches, so a sender that must not lose its first
        messages waits here instead of sleeping a guessed time.
        """
        matched = threading.Event()

        def on_status(status: Any) -> None:
            if status.matching:
                matched.set()

        listener = self._inner.declare_matching_listener(on_status)
        try:
            # a MatchingStatus, always truthy (its stub says bool): its `matching` field is the answer
            status: Any = self._inner.matching_status
            return bool(getattr(status, "matching", status)) or matched.wait(timeout_s)
        finally:
            listener.undeclare()  # type: ignore[no-untyped-call]

    def close(self) -> None:
        self._inner.undeclare()  # type: ignore[no-untyped-call]


class ZenohToken:
    def __init__(self, inner: zenoh.LivelinessToken) -> None:
        self._inner: zenoh.LivelinessToken | None = inner

    def close(self) -> None:
        if self._inner is not None:
            self._inner.undeclare()  # type: ignore[no-untyped-call]
            self._inner = None


class ZenohBus:
    """A zenoh session seen through the few operations dynqos needs (the `Bus` protocol)."""

    def __init__(self, session: zenoh.Session, clock: Clock | None = None) -> None:
        self._session = session
        self._clock = clock or MonotonicClock()
        self._subscribers: list[Any] = []
        self._declared: dict[tuple[str, int], Any] = {}  # (key_expr, id(stats)) -> its subscriber
        self.subscriptions: list[SubscriptionStats] = []
        self._lock = threading.Lock()

    @property
    def session(self) -> zenoh.Session:
        return self._session

    def publisher(
        self, key: str, priority: Priority, *, drop_when_congested: bool = False, express: bool = False
    ) -> ZenohPublisher:
        congestion = zenoh.CongestionControl.DROP if drop_when_congested else zenoh.CongestionControl.BLOCK
        inner = self._session.declare_publisher(
            key, priority=_ZENOH_PRIORITY[priority], congestion_control=congestion, express=express
        )
        return ZenohPublisher(inner, key)

    def subscribe(
        self,
        key_expr: str,
        queue: BoundedQueue[Received],
        *,
        expect: tuple[type[Message], ...] = (),
        decoder: Callable[[bytes], Message] = decode,
        remote_only: bool = False,
        stats: SubscriptionStats | None = None,
        direct: bool = False,
    ) -> SubscriptionStats:
        """Decode every sample on key_expr into `queue`; bad payloads are counted, never raised.
        `remote_only`: not what this session itself publishes (zenoh drops those before any decoding).
        `stats`: counters shared with other subscribers (one per drone, counted as one stream).
        `direct`: decode on zenoh's receiving thread. Otherwise zenoh-python hands each subscriber's
        samples to a Python thread of its own, and a replica that follows 75 drones with three
        subscribers each ran 225 threads fighting for the GIL (commands seconds late at 150 drones)."""
        stats = stats or SubscriptionStats(key_expr)
        clock = self._clock
        deliver = delivery(queue, stats, expect, decoder)

        def on_sample(sample: zenoh.Sample) -> None:
            deliver(str(sample.key_expr), sample.payload.to_bytes(), clock.now_ns())

        origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
        handler = zenoh.handlers.Callback(on_sample, indirect=False) if direct else on_sample
        subscriber = self._session.declare_subscriber(key_expr, handler, allowed_origin=origin)
        with self._lock:
            self._subscribers.append(subscriber)
            self._declared[(key_expr, id(stats))] = subscriber
            if all(s is not stats for s in self.subscriptions):
                self.subscriptions.append(stats)
        return stats

    def subscribe_newest(
        self, key_expr: str, *, expect: tuple[type[Message], ...] = (), stats: SubscriptionStats | None = None
    ) -> Newest:
        stats = stats or SubscriptionStats(key_expr)
        subscriber = self._session.declare_subscriber(key_expr, zenoh.handlers.RingChannel(1))
        with self._lock:
            self._subscribers.append(subscriber)

        def take_raw() -> tuple[str, bytes] | None:
            sample = subscriber.try_recv()
            return None if sample is None else (str(sample.key_expr), sample.payload.to_bytes())

        def close() -> None:
            with self._lock:
                if subscriber not in self._subscribers:
                    return  # the session closed it already
                self._subscribers.remove(subscriber)
            subscriber.undeclare()  # type: ignore[no-untyped-call]

        return Newest(take_raw, close, stats, expect, self._clock)

    def unsubscribe(self, key_expr: str, stats: SubscriptionStats) -> None:
        with self._lock:
            subscriber = self._declared.pop((key_expr, id(stats)), None)
            if subscriber is not None:
                self._subscribers.remove(subscriber)
        if subscriber is not None:
            subscriber.undeclare()

    def declare_token(self, key: str) -> ZenohToken:
        """A liveliness token; the router withdraws it when this session closes or its process dies."""
        return ZenohToken(self._session.liveliness().declare_token(key))

    def watch_tokens(self, key_expr: str, on_change: Callable[[str, bool], None]) -> None:
        """Tokens already present (zenoh's history), then every appearance and withdrawal."""

        def on_sample(sample: zenoh.Sample) -> None:
            on_change(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        subscriber = self._session.liveliness().declare_subscriber(key_expr, on_sample, history=True)
        with self._lock:
            self._subscribers.append(subscriber)

    def alive_tokens(self, key_expr: str, timeout_s: float) -> list[str]:
        """The tokens present now, as the router knows them (a liveliness query; ends when it answers)."""
        replies = self._session.liveliness().get(key_expr, timeout=timeout_s)
        return [str(reply.ok.key_expr) for reply in replies if reply.ok is not None]

    @property
    def zid(self) -> str:
        return str(self._session.info.zid())

    def raw_subscribe(
        self, key_expr: str, on_payload: Callable[[str, bytes], None], *, direct: bool = False
    ) -> None:
        """`on_payload(key, payload)` for every sample on `key_expr`, undecoded (the ROS 2 bridge's).
        `direct`: on zenoh's receiving thread, no Python thread of its own (for a callback that only
        notes what came, like the replicas' heartbeats)."""

        def on_sample(sample: zenoh.Sample) -> None:
            on_payload(str(sample.key_expr), sample.payload.to_bytes())

        handler = zenoh.handlers.Callback(on_sample, indirect=False) if direct else on_sample
        subscriber = self._session.declare_subscriber(key_expr, handler)
        with self._lock:
            self._subscribers.append(subscriber)

    def links(self) -> list[LinkInfo]:
        return [LinkInfo(link.src, link.dst, link.priorities) for link in self._session.info.links()]

    def close(self) -> None:
        with self._lock:
            subscribers, self._subscribers = self._subscribers, []
            self._declared.clear()
        for subscriber in subscribers:
            subscriber.undeclare()
        close_session(self._session, "bus")

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


SESSION_CLOSE_S = 5.0


def close_session(session: Any, name: str, within_s: float = SESSION_CLOSE_S) -> bool:
    """Close a zenoh session, waiting at most `within_s`; False (and one warning) if it did not finish.

    A close that waits on a peer can hang (it was seen once in a router after SIGTERM, past the runner's
    15 s stop timeout, which then SIGKILLed it); bounding it lets the process report and exit on its own.
    """
    done = threading.Event()

    def close() -> None:
        try:
            session.close()
        except zenoh.ZError as exc:  # e.g. "close operation timed out": reported, the process is stopping
            log.warning("%s: zenoh session close failed: %s", name, exc)
        done.set()

    threading.Thread(target=close, name=f"{name}-close", daemon=True).start()
    if done.wait(within_s):
        return True
    log.warning("%s: zenoh session close did not finish in %.0f s; exiting without it", name, within_s)
    return False


def open_session(
    cfg: ZenohConfig,
    role: Role,
    *,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    client: bool = False,
    lease_s: float | None = None,
) -> zenoh.Session:
    """Open a zenoh session, turning zenoh's errors into one TransportError that names the endpoints."""
    zcfg = session_config(cfg, role, connect=connect, listen=listen, client=client, lease_s=lease_s)
    try:
        return zenoh.open(zcfg)
    except zenoh.ZError as exc:
        connect_to, listen_on = endpoints(cfg, role, connect, listen)
        first_line = str(exc).split(" at /", 1)[0]
        raise TransportError(
            f"cannot open zenoh {role.value} session (connect {connect_to}, listen {listen_on}): {first_line}"
        ) from None


def open_bus(
    cfg: ZenohConfig,
    role: Role,
    *,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    clock: Clock | None = None,
    client: bool = False,
    lease_s: float | None = None,
) -> ZenohBus:
    session = open_session(cfg, role, connect=connect, listen=listen, client=client, lease_s=lease_s)
    return ZenohBus(session, clock)
