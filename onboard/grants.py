"""The QoS agents' answers as the drone keeps them: the last grant from each edge site. Pure.

With one site (every grant's `site` is "") this is the agent's last word, as it always was. A drone on
two paths asks each site's agent for its own path (each agent its own operator, docs/multipath.md) and
hears both agents by both paths: its priority counts as granted when either site grants it (the
Commands it flies come by whichever path answers first), and as denied only when every site heard
within [qos] agent_timeout_s denies it; each path's own PFSM reads its own site's grant (`of`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from dynqos.common.messages import QosGrant
from dynqos.common.modes import Grant
from dynqos.onboard.tick import LogEvent

MAX_SITES = 8  # sites whose grant is kept; a ninth name is ignored (a drone has at most MAX_PATHS)
# how much a grant gives the drone, for the best of several sites' answers
_RANK = {Grant.NONE: 0, Grant.UNAVAILABLE: 1, Grant.REQUESTED: 2, Grant.AVAILABLE: 3}


@dataclass
class SiteGrants:
    agent_timeout_ns: int
    last: dict[str, tuple[Grant, int]] = field(default_factory=dict)  # site -> (grant, heard at)

    def take(self, grant: QosGrant, arrival_ns: int) -> LogEvent | None:
        """Keep `grant` as its site's last word; what the log says when that word changed."""
        if grant.site not in self.last and len(self.last) >= MAX_SITES:
            return None
        before = self.last.get(grant.site, (Grant.NONE, arrival_ns))[0]
        self.last[grant.site] = (grant.grant, arrival_ns)
        if grant.grant is before:
            return None
        why = f" ({grant.reason})" if grant.reason else ""
        at = f" at site {grant.site}" if grant.site else ""
        level = logging.WARNING if grant.grant is Grant.UNAVAILABLE else logging.INFO
        return LogEvent(level, f"qos: the network's grant{at} is {grant.grant.value}{why}")

    def _heard(self, now_ns: int) -> list[Grant]:
        return [grant for grant, at in self.last.values() if now_ns - at <= self.agent_timeout_ns]

    def agent_heard(self, now_ns: int) -> bool:
        """An agent answered within the timeout (else: links only, nobody asks the network)."""
        return bool(self._heard(now_ns))

    def of(self, site: str, now_ns: int) -> Grant:
        """`site`'s own last grant, if its agent was heard within the timeout (else NONE)."""
        grant, at = self.last.get(site, (Grant.NONE, now_ns))
        return grant if now_ns - at <= self.agent_timeout_ns else Grant.NONE

    def reported(self, now_ns: int) -> Grant:
        """The best grant of the sites heard within the timeout (NONE when none was)."""
        return max(self._heard(now_ns), key=_RANK.__getitem__, default=Grant.NONE)
