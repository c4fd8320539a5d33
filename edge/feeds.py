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
thread and wait, bounded, in a map. Every drone's subscriber of one input shares one SubscriptionStats,
so the metrics count an input, not a drone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from dynqos.common import keys
from dynqos.common.acl import reserved_name
from dynqos.common.bus import Bus, Received, SubscriptionStats
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Command, Message, MissionRequest, Reference, State
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
    stats: SubscriptionStats = field(default_factory=SubscriptionStats)


def states() -> Feed:
    return Feed(
        lambda uav: keys.uplink_any_flow(uav, Stream.STATE), keys.uplink_all_drones(Stream.STATE), (State,)
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


def commands() -> Feed:
    """Other replicas' commands (ours never: zenoh drops them before decoding)."""
    return Feed(
        lambda uav: keys.downlink(uav, Downlink.COMMAND),
        keys.downlink_all_drones(Downlink.COMMAND),
        (Command,),
        remote_only=True,
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

    def reconcile(self, wanted: Callable[[str], bool], *, assignment_changed: bool) -> None:
        """The worker: subscribe to each present drone `wanted` says this replica serves or stands by
        for, unsubscribe from the others and from drones that went."""
        if not self.presence.take() and not assignment_changed:
            return
        want = {uav for uav in self.present if wanted(uav)}
        for uav in want - self.subscribed:
            for feed in self.feeds:
                # direct: no Python thread per subscriber (three per drone would be hundreds)
                self.bus.subscribe(
                    feed.key(uav),
                    self.queue,
                    expect=feed.expect,
                    remote_only=feed.remote_only,
                    stats=feed.stats,
                    direct=True,
                )
            log.info("%s: following drone %s (%d followed)", self.service, uav, len(self.subscribed) + 1)
            self.subscribed.add(uav)
        for uav in self.subscribed - want:
            for feed in self.feeds:
                self.bus.unsubscribe(feed.key(uav), feed.stats)
            self.subscribed.discard(uav)
            why = "its token went" if uav not in self.present else "not ours now"
            log.info("%s: no longer following drone %s (%s)", self.service, uav, why)

    def rejected(self) -> int:
        return sum(feed.stats.rejected for feed in self.feeds)
