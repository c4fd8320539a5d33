"""The drone's sessions to the edge: one per path (docs/multipath.md), each with its publishers and
what it delivered, and the endpoints each path dials for its default and priority flow."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from dynqos.common.bus import Bus, Received, SubscriptionStats, Token
from dynqos.common.config import Config
from dynqos.common.keys import Downlink, Stream
from dynqos.common.messages import Message, QosRequest, State
from dynqos.common.queues import BoundedQueue
from dynqos.common.transport import default_flow_endpoint, priority_flow_endpoint
from dynqos.onboard.camera_stream import FlowPublishers


@dataclass
class Inbox:
    """What one path delivers, by kind, each bounded on its own: acks never crowd out Commands."""

    commands: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(256))
    camera_replies: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(512))
    references: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(16))
    grants: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(16))  # the QoS agent's
    tasks: BoundedQueue[Received] = field(default_factory=lambda: BoundedQueue(64))  # the user's tasks'

    def drain(self) -> list[Received]:
        return (
            self.commands.drain()
            + self.camera_replies.drain()
            + self.references.drain()
            + self.grants.drain()
            + self.tasks.drain()
        )


@dataclass
class PathLink:
    """One of the drone's paths: its session, its publishers and what it delivered."""

    name: str  # "" for a drone's only path
    bus: Bus
    publishers: dict[Stream, FlowPublishers] = field(default_factory=dict)
    inbox: Inbox = field(default_factory=Inbox)
    downlink_stats: dict[Downlink, SubscriptionStats] = field(default_factory=dict)
    presence: Token | None = None


def flow_endpoints(config: Config) -> list[str]:
    """The router's endpoints for the default and the priority flow, as a drone on one path dials them."""
    return _endpoints(config, config.onboard.connect_default, config.onboard.connect_priority)


def path_endpoints(config: Config) -> dict[str, list[str]]:
    """Each path's endpoints for its default and priority flow, by path name ("": the only path)."""
    paths = config.onboard.paths
    if not paths:
        return {"": flow_endpoints(config)}
    return {p.name: _endpoints(config, p.connect_default, p.connect_priority) for p in paths}


def _endpoints(config: Config, connect_default: str, connect_priority: str) -> list[str]:
    z = config.zenoh
    out = []
    for override, build, port in (
        (connect_default, default_flow_endpoint, z.default_port),
        (connect_priority, priority_flow_endpoint, z.priority_port),
    ):
        if override:
            host, _, p = override.rpartition(":")
            out.append(build(z, host=host.strip("[]"), port=int(p)))
        else:
            out.append(build(z, port=port))
    return out


def as_carried(message: Message, path: str, sites: dict[str, str]) -> Message:
    """`message` as `path` carries it (`sites`: each path's site): a QoS request names the site whose
    agent it is for, so each site's agent asks its own operator for its own path; a State names its
    path, so each site answers each copy and the drone times each path's uplink; the rest as it is."""
    if path and isinstance(message, QosRequest):
        return replace(message, site=sites.get(path, path))
    if path and isinstance(message, State):
        return replace(message, path=path)
    return message
