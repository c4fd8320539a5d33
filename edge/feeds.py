"""Each replica of an edge service subscribes to the drones it flies or stands by for, and to no other.

Subscribing to every drone's keys with one wildcard made every replica receive and decode every
drone's states to drop most of them. Instead a drone announces itself with a liveliness token
(`dynqos/<uav>/alive`, held by the onboard daemon while its session lives, withdrawn by the router when
it goes); a replica watches those tokens and, for each present drone that its assignment gives it
(primary, standby or the replica holding it), declares one subscriber per input on that drone's own
keys. The router then sends a replica only its drones' traffic, which matters most when replicas run
on two sites. A drone that holds no token is served by no MPC or planner (docs/reliability.md).

The set is reconciled on the service's worker thread when a drone comes or goes, and when the caller
says its assignment changed (a replica joined or left, a role changed); token changes arrive on zenoh's
thread and wait, bounded, in a map. A drone the caller only stands by for (`quiet`) has its pullable
input kept newest-only instead (`Bus.subscribe_newest`), read when the caller pulls, and on the feed's
`quiet_key` where it has one: an MPC standby needs a drone's newest state and term now and then (and
its newest at once on a takeover), not a Python call for each state. Every drone's subscriber of one
input shares one SubscriptionStats, so the metrics count an input, not a drone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from dynqos.common import keys
from dynqos.common.acl import reserved_name
from dynqos.common.bus import Bus, Newest, Received, SubscriptionStats
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Message, MissionRequest, Reference, State
from dynqos.common.queues import BoundedQueue
from dynqos.edge.presence import Presence, Watch

log = logging.getLogger(__name__)

MAX_DRONES = 4096  # present drones a replica tracks; a token flood beyond is refused and counted
MAX_PENDING_CHANGES = 2 * MAX_DRONES  # presence changes waiting for the worker (a fleet starting at once)


@dataclass(frozen=True)
class Feed:
    """One input of a service, per drone: its key, what may arrive there, and whether our own
    publications on it are delivered to us (`remote_only`: not)."""

    key: Callable[[str], str]  # the drone's key
    all_drones: str  # every drone's (the metrics' label)
    expect: tuple[type[Message], ...]
    remote_only: bool = False
    pullable: bool = False  # for a quiet drone, kept newest-only and pulled (not with remote_only)
    quiet_key: Callable[[str], str] | None = None  # where a quiet drone's input is pulled from (else `key`)
    stats: SubscriptionStats = field(default_factory=SubscriptionStats)


def states(*, pullable: bool = False, quiet_key: Callable[[str], str] | None = None) -> Feed:
    return Feed(
        lambda uav: keys.uplink_any_flow(uav, Stream.STATE),
        keys.uplink_all_drones(Stream.STATE),
        (State,),
        pullable=pullable,
        quiet_key=quiet_key,
    )


def references(*, remote_only: bool = False) -> Feed:
    return Feed(
        lambda uav: keys.downlink(uav, Downlink.REFERENCE),
        keys.downlink_all_drones(Downlink.REFERENCE),
        (Reference,),
        remote_only,
    )


def missions() -> Feed:
    """Missions from outside the edge (the ROS 2 bridge's MissionRequest) for the drones followed."""
    return Feed(
        lambda uav: keys.downlink(uav, Downlink.MISSION),
        keys.downlink_all_drones(Downlink.MISSION),
        (MissionRequest,),
    )


def drone_id(uav: str) -> bool:
    """A drone's id as its presence token names it: the id rule, and never an edge service's name."""
    return keys.UAV_ID_PATTERN.fullmatch(uav) is not None and not reserved_name(uav)


class DroneFeeds:
    def __init__(self, service: str, bus: Bus, queue: BoundedQueue[Received], feeds: list[Feed]) -> None:
        self.service = service
        self.bus = bus
        self.queue = queue
        self.feeds = feeds
        self.subscribed: set[str] = set()
        self.pulled: dict[str, Newest] = {}  # quiet drones: their pullable input, newest-only
        if sum(feed.pullable for feed in feeds) > 1:
            raise ValueError("at most one pullable feed")
        for feed in feeds:
            feed.stats.key_expr = feed.all_drones
            bus.subscriptions.append(feed.stats)
        drones = Watch("drone", keys.drones_present(), keys.uav_of_presence)
        self.presence = Presence(
            bus, service, [drones], pending_limit=MAX_PENDING_CHANGES, valid=drone_id, cap=MAX_DRONES
        )
        self.present = self.presence.present["drone"]

    @property
    def refused(self) -> int:
        """Presence tokens refused: an invalid or edge id, beyond MAX_DRONES, or a flood of changes."""
        return self.presence.refused

    def reconcile(
        self,
        wanted: Callable[[str], bool],
        *,
        assignment_changed: bool,
        quiet: Callable[[str], bool] | None = None,
    ) -> None:
        """The worker: subscribe to each present drone `wanted` says this replica serves or stands by
        for (its pullable input newest-only while `quiet` says so), unsubscribe from the others and
        from drones that went."""
        if not self.presence.take() and not assignment_changed:
            return
        want = {uav for uav in self.present if wanted(uav)}
        for uav in want:
            pull = quiet is not None and quiet(uav)
            if uav not in self.subscribed:
                for feed in self.feeds:
                    self._declare(uav, feed, pull=pull and feed.pullable)
                log.info("%s: following drone %s (%d followed)", self.service, uav, len(self.subscribed) + 1)
                self.subscribed.add(uav)
            elif pull != (uav in self.pulled):  # declared anew before the old one goes: no gap
                for feed in (f for f in self.feeds if f.pullable):
                    old = self.pulled.pop(uav, None)
                    self._declare(uav, feed, pull=pull)
                    if old is not None:
                        old.close()
                    else:
                        self.bus.unsubscribe(feed.key(uav), feed.stats)
        for uav in self.subscribed - want:
            pulled = self.pulled.pop(uav, None)
            if pulled is not None:
                pulled.close()
            for feed in self.feeds:
                if not (feed.pullable and pulled is not None):
                    self.bus.unsubscribe(feed.key(uav), feed.stats)
            self.subscribed.discard(uav)
            why = "its token went" if uav not in self.present else "not ours now"
            log.info("%s: no longer following drone %s (%s)", self.service, uav, why)

    def _declare(self, uav: str, feed: Feed, *, pull: bool) -> None:
        if pull:
            key = (feed.quiet_key or feed.key)(uav)
            self.pulled[uav] = self.bus.subscribe_newest(key, expect=feed.expect, stats=feed.stats)
            return
        # direct: no Python thread per subscriber (three per drone would be hundreds)
        self.bus.subscribe(
            feed.key(uav),
            self.queue,
            expect=feed.expect,
            remote_only=feed.remote_only,
            stats=feed.stats,
            direct=True,
        )

    def pull(self, only: Callable[[str], bool] | None = None) -> list[Received]:
        """The quiet drones' newest inputs since the last pull (of the drones `only` says, if given)."""
        return [
            item
            for uav, newest in self.pulled.items()
            if (only is None or only(uav)) and (item := newest.take()) is not None
        ]

    def rejected(self) -> int:
        return sum(feed.stats.rejected for feed in self.feeds)
