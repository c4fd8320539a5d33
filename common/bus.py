"""The publish/subscribe seam: what dynqos code sees of the network, with an in-memory implementation.

Pure and I/O code alike publish through a `Publisher` and receive through `Bus.subscribe` into a
bounded queue; neither sees zenoh. `common.transport.ZenohBus` is the real implementation over a zenoh
session (httpx's transport split is the model). `MemoryBus` delivers within one process, through the
same codec and the same checks, so a test can drive the onboard core, the MPC or a whole closed loop
without sockets and on a fake clock.
"""

from __future__ import annotations

import enum
import logging
import re
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from dynqos.common.clock import Clock, MonotonicClock
from dynqos.common.errors import DecodeError
from dynqos.common.floods import worth_logging
from dynqos.common.messages import Message, decode, encode
from dynqos.common.queues import BoundedQueue

log = logging.getLogger(__name__)


class Priority(enum.IntEnum):
    """Zenoh's priorities, numbered as zenoh numbers them (1 = REAL_TIME)."""

    REAL_TIME = 1
    INTERACTIVE_HIGH = 2
    INTERACTIVE_LOW = 3
    DATA_HIGH = 4
    DATA = 5
    DATA_LOW = 6
    BACKGROUND = 7


@dataclass(frozen=True, slots=True)
class Received:
    """One decoded message as handed from a subscription to the consumer."""

    key: str
    message: Message
    arrival_ns: int
    path: str = ""  # which of a drone's paths it came by (docs/multipath.md; "" = its only one)


class SubscriptionStats:
    """Counters of one subscription; written by the delivering thread, read by anyone (the health line,
    the metrics)."""

    def __init__(self, key_expr: str = "") -> None:
        self.key_expr = key_expr
        self.received = 0
        self.rejected = 0
        self.rejected_by_cause: dict[str, int] = {}  # undecodable, unexpected_type, wrong_drone
        self.last_error: str | None = None

    def reject(self, cause: str, error: str) -> None:
        self.rejected += 1
        self.rejected_by_cause[cause] = self.rejected_by_cause.get(cause, 0) + 1
        self.last_error = error


class Publisher(Protocol):
    """Publishes messages on one key with a priority fixed at declaration (zenoh's rule)."""

    key: str
    sent: int  # messages put
    sent_bytes: int  # their encoded bytes, as handed to the session (zenoh's own framing not counted)

    def put(self, message: Message) -> None: ...

    def put_bytes(self, data: bytes, attachment: bytes | None = None) -> None: ...

    def close(self) -> None: ...


class Token(Protocol):
    """A liveliness token: present on the bus while held, gone when closed or when its process dies."""

    def close(self) -> None: ...


# (key, alive): called once per token already present, then once per change
TokenWatcher = Callable[[str, bool], None]
# (key, payload, arrival_ns): what a subscriber's receive path is handed
Deliver = Callable[[str, bytes, int], None]


class Bus(Protocol):
    """A session seen through the few operations dynqos needs."""

    subscriptions: list[SubscriptionStats]  # one per subscribe(), for the metrics

    def publisher(
        self, key: str, priority: Priority, *, drop_when_congested: bool = False, express: bool = False
    ) -> Publisher: ...

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
    ) -> SubscriptionStats: ...

    def unsubscribe(self, key_expr: str, stats: SubscriptionStats) -> None:
        """Undeclare the subscriber declared on `key_expr` with `stats` (none: nothing happens)."""

    def subscribe_newest(
        self, key_expr: str, *, expect: tuple[type[Message], ...] = (), stats: SubscriptionStats | None = None
    ) -> Newest:
        """Keep only the newest sample on `key_expr` until it is taken, without a Python call per sample
        (zenoh: a one-slot ring in Rust): for what is read now and then, not answered (an MPC standby's
        view of the drones it stands by for)."""
        ...

    def declare_token(self, key: str) -> Token: ...

    def watch_tokens(self, key_expr: str, on_change: TokenWatcher) -> None: ...

    def alive_tokens(self, key_expr: str, timeout_s: float) -> list[str]: ...

    def close(self) -> None: ...


class RawBus(Bus, Protocol):
    """A Bus that also carries another system's payloads as they are: the ROS 2 bridge's rmw_zenoh
    samples, which are CDR with an attachment, not dynqos messages."""

    @property
    def zid(self) -> str:
        """The session's zenoh id (what rmw_zenoh names a node's session by)."""
        ...

    def raw_subscribe(
        self, key_expr: str, on_payload: Callable[[str, bytes], None], *, direct: bool = False
    ) -> None:
        """`on_payload(key, payload)` on zenoh's thread for every sample (ours too); it must not block.
        `direct`: on the receiving thread itself, no Python thread of its own."""
        ...


class Newest:
    """The newest sample on a key, decoded when taken through the one receive path (`delivery`)."""

    def __init__(
        self,
        take_raw: Callable[[], tuple[str, bytes] | None],
        close: Callable[[], None],
        stats: SubscriptionStats,
        expect: tuple[type[Message], ...],
        clock: Clock,
    ) -> None:
        self._take_raw = take_raw
        self._close = close
        self._clock = clock
        self._slot: BoundedQueue[Received] = BoundedQueue(1)
        self._deliver = delivery(self._slot, stats, expect, decode)

    def take(self) -> Received | None:
        """The newest sample since the last take (None: nothing new, or it was rejected and counted);
        its arrival time is now (it waited in the slot)."""
        raw = self._take_raw()
        if raw is None:
            return None
        self._deliver(raw[0], raw[1], self._clock.now_ns())
        return self._slot.get_nowait()

    def poll(self) -> bool:
        """Whether a sample came since the last take or poll, unread (a heartbeat says so by coming)."""
        return self._take_raw() is not None

    def close(self) -> None:
        self._close()


def delivery(
    queue: BoundedQueue[Received],
    stats: SubscriptionStats,
    expect: tuple[type[Message], ...],
    decoder: Callable[[bytes], Message],
) -> Callable[[str, bytes, int], None]:
    """The one receive path of every Bus: decode, check, count, hand off; never raises, never blocks.

    With `expect`, a well-formed message of another type is rejected too, and so is one whose drone id
    differs from the one in its key (a drone speaking for another)."""

    def deliver(key: str, payload: bytes, arrival_ns: int) -> None:
        cause = "undecodable"
        try:
            message = decoder(payload)
            cause = "unexpected_type"
            if expect and not isinstance(message, expect):
                raise DecodeError("t", f"a {message.TYPE} is not expected here")
            cause = "wrong_drone"
            if expect and key.split("/", 2)[1] != message.uav:
                raise DecodeError("uav", f"drone {message.uav!r} on another drone's key")
        except DecodeError as exc:
            stats.reject(cause, str(exc))
            if worth_logging(stats.rejected):
                log.warning("rejected message on %s (%d so far): %s", key, stats.rejected, exc)
            return
        stats.received += 1
        queue.put(Received(key, message, arrival_ns))

    return deliver


def key_matcher(key_expr: str) -> re.Pattern[str]:
    """A regular expression for a zenoh key expression: `*` is one chunk, `**` any number of chunks."""
    parts = []
    for chunk in key_expr.split("/"):
        if chunk == "**":
            parts.append("(?:[^/]+(?:/[^/]+)*)?")
        elif chunk == "*":
            parts.append("[^/]+")
        else:
            parts.append(re.escape(chunk))
    pattern = "/".join(parts).replace("/(?:[^/]+(?:/[^/]+)*)?", "(?:/[^/]+)*")
    return re.compile(pattern)


class MemoryPublisher:
    def __init__(self, bus: MemoryBus, key: str) -> None:
        self._bus = bus
        self.key = key
        self.sent = 0
        self.sent_bytes = 0

    def put(self, message: Message) -> None:
        self.put_bytes(encode(message))

    def put_bytes(self, data: bytes, attachment: bytes | None = None) -> None:
        self._bus.deliver(self.key, data)
        self.sent += 1
        self.sent_bytes += len(data)

    def close(self) -> None:
        pass


class MemoryToken:
    def __init__(self, bus: MemoryBus, key: str) -> None:
        self._bus, self.key, self.closed = bus, key, False

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._bus._token_changed(self.key, alive=False)


class MemoryBus:
    """Every subscriber of the process, matched by key expression; puts are delivered in order.

    Messages cross the real codec, so what arrives is what would arrive over zenoh. `delays` gives a
    one-way delay to the keys that match a key expression (the first match counts; say which traffic
    crosses the network, e.g. `("dynqos/*/up/**", 10_000_000)`): such a put is held and `pump()`
    delivers it when it is due on the bus clock, which a test on a fake clock controls. Other puts are
    delivered at once. Several components (a drone's core, the MPC, an observer) can share one bus."""

    def __init__(self, clock: Clock | None = None, *, delays: Sequence[tuple[str, int]] = ()) -> None:
        if any(ns < 0 for _, ns in delays):
            raise ValueError(f"delays must be >= 0 ns, got {list(delays)}")
        self._clock = clock or MonotonicClock()
        self._delays = [(key_matcher(expr), ns) for expr, ns in delays]
        # (pattern, delivery, (key_expr, id(stats))): the last names the subscriber for unsubscribe()
        self._subscribers: list[tuple[re.Pattern[str], Deliver, tuple[str, int]]] = []
        self.subscriptions: list[SubscriptionStats] = []
        self._in_flight: deque[tuple[int, str, bytes]] = deque()
        self._lock = threading.Lock()
        self.published: dict[str, int] = {}  # key -> messages put (delivered or not)
        self._tokens: dict[str, int] = {}  # key -> how many holders
        self._token_watchers: list[tuple[re.Pattern[str], TokenWatcher]] = []

    def publisher(
        self, key: str, priority: Priority, *, drop_when_congested: bool = False, express: bool = False
    ) -> MemoryPublisher:
        return MemoryPublisher(self, key)

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
        """`remote_only` and `direct` have no meaning within one process: everything is delivered, on
        the putter's thread (a subscriber that asks for remote_only must, and does, tolerate its own
        messages)."""
        stats = stats or SubscriptionStats(key_expr)
        with self._lock:
            deliver = delivery(queue, stats, expect, decoder)
            self._subscribers.append((key_matcher(key_expr), deliver, (key_expr, id(stats))))
            if all(s is not stats for s in self.subscriptions):
                self.subscriptions.append(stats)
        return stats

    def subscribe_newest(
        self, key_expr: str, *, expect: tuple[type[Message], ...] = (), stats: SubscriptionStats | None = None
    ) -> Newest:
        stats = stats or SubscriptionStats(key_expr)
        slot: list[tuple[str, bytes]] = []

        def keep(key: str, data: bytes, _ns: int) -> None:
            slot[:] = [(key, data)]

        def take_raw() -> tuple[str, bytes] | None:
            return slot.pop() if slot else None

        entry = (key_matcher(key_expr), keep, (key_expr, -1))

        def close() -> None:
            with self._lock:
                if entry in self._subscribers:
                    self._subscribers.remove(entry)

        with self._lock:
            self._subscribers.append(entry)
        return Newest(take_raw, close, stats, expect, self._clock)

    def unsubscribe(self, key_expr: str, stats: SubscriptionStats) -> None:
        with self._lock:
            self._subscribers = [s for s in self._subscribers if s[2] != (key_expr, id(stats))]

    zid = "0123456789abcdef0123456789abcdef"  # a session id, for what names itself by one (rmw_zenoh)

    def raw_subscribe(
        self, key_expr: str, on_payload: Callable[[str, bytes], None], *, direct: bool = False
    ) -> None:
        with self._lock:
            self._subscribers.append(
                (key_matcher(key_expr), lambda key, data, _ns: on_payload(key, data), (key_expr, 0))
            )

    def declare_token(self, key: str) -> MemoryToken:
        self._token_changed(key, alive=True)
        return MemoryToken(self, key)

    def watch_tokens(self, key_expr: str, on_change: TokenWatcher) -> None:
        pattern = key_matcher(key_expr)
        with self._lock:
            self._token_watchers.append((pattern, on_change))
            present = [key for key in self._tokens if pattern.fullmatch(key)]
        for key in present:
            on_change(key, True)

    def alive_tokens(self, key_expr: str, timeout_s: float) -> list[str]:
        pattern = key_matcher(key_expr)
        with self._lock:
            return [key for key in self._tokens if pattern.fullmatch(key)]

    def _token_changed(self, key: str, *, alive: bool) -> None:
        """zenoh's rule: a key is alive while any token holds it; watchers hear only the edges."""
        with self._lock:
            before = self._tokens.get(key, 0)
            after = before + (1 if alive else -1)
            if after > 0:
                self._tokens[key] = after
            else:
                self._tokens.pop(key, None)
            watchers = [w for pattern, w in self._token_watchers if pattern.fullmatch(key)]
        if (before == 0) != (after <= 0):
            for watcher in watchers:
                watcher(key, alive)

    def deliver(self, key: str, data: bytes) -> None:
        with self._lock:
            self.published[key] = self.published.get(key, 0) + 1
            delay_ns = next((ns for pattern, ns in self._delays if pattern.fullmatch(key)), 0)
            if delay_ns:
                self._in_flight.append((self._clock.now_ns() + delay_ns, key, data))
                return
        self._hand_over(key, data)

    def pump(self) -> int:
        """Deliver every held message that is due now; returns how many were."""
        now = self._clock.now_ns()
        due = []
        with self._lock:
            while self._in_flight and self._in_flight[0][0] <= now:
                due.append(self._in_flight.popleft())
        for _, key, data in due:
            self._hand_over(key, data)
        return len(due)

    def _hand_over(self, key: str, data: bytes) -> None:
        with self._lock:
            targets = [deliver for pattern, deliver, _ in self._subscribers if pattern.fullmatch(key)]
        now = self._clock.now_ns()
        for deliver in targets:
            deliver(key, data, now)

    def close(self) -> None:
        with self._lock:
            self._subscribers.clear()
            self._in_flight.clear()
            self._token_watchers.clear()
