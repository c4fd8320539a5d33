"""Whose a State is: the MPC replica's static shard, the term and replica the drone follows at a site,
and whether a State is newer news than the holder's copy of it. Pure."""

from __future__ import annotations

import zlib

from dynqos.common import keys
from dynqos.common.bus import Received
from dynqos.common.messages import State


def shard_of(uav: str, shard_count: int) -> int:
    """The MPC replica that serves `uav`: stable across processes and restarts (unlike hash())."""
    return zlib.crc32(uav.encode()) % shard_count


def own_after_copy(previous: Received, item: Received) -> bool:
    """The drone's own State after the holder's copy of it: newer news (it is answered, the copy not)."""
    return (
        item.message.seq == previous.message.seq
        and keys.is_state_watch(previous.key)
        and not keys.is_state_watch(item.key)
    )


def followed_at(state: State, site: str) -> tuple[int, str]:
    """The term and replica the drone follows at `site` ("": the one site, the State's own fields)."""
    if not site:
        return state.command_term, state.command_replica
    return next(((term, replica) for s, term, replica in state.controllers if s == site), (0, ""))
