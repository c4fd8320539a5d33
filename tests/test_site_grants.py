"""The drone's view of the QoS agents' grants, one per edge site (onboard/grants.py): with one site the
agent's last word as before; with two, granted when either site grants, denied only when every site
heard denies, and a site not heard within the agent timeout no longer counts. And each path's QoS
request names its own site."""

from __future__ import annotations

import logging

from dynqos.common.messages import QosGrant, QosRequest
from dynqos.common.modes import Grant
from dynqos.onboard.grants import MAX_SITES, SiteGrants
from dynqos.onboard.links import as_carried

MS = 1_000_000


def grant(state: Grant, site: str = "", reason: str = "") -> QosGrant:
    return QosGrant(uav="uav1", seq=1, grant=state, backend="camara", site=site, reason=reason)


def test_one_site_is_the_agents_last_word_and_is_forgotten_after_the_timeout() -> None:
    grants = SiteGrants(agent_timeout_ns=1_000 * MS)
    assert (grants.agent_heard(0), grants.reported(0)) == (False, Grant.NONE)
    assert grants.take(grant(Grant.NONE), 0) is None  # nothing changed: nothing to log
    event = grants.take(grant(Grant.UNAVAILABLE, reason="409"), 10 * MS)
    assert event is not None
    assert (event.level, event.text) == (logging.WARNING, "qos: the network's grant is unavailable (409)")
    assert grants.take(grant(Grant.UNAVAILABLE), 20 * MS) is None
    assert grants.reported(500 * MS) is Grant.UNAVAILABLE
    assert grants.reported(1_021 * MS) is Grant.NONE  # the agent went quiet
    assert not grants.agent_heard(1_021 * MS)


def test_two_sites_the_best_grant_counts_and_denied_only_when_both_deny() -> None:
    grants = SiteGrants(agent_timeout_ns=1_000 * MS)
    grants.take(grant(Grant.UNAVAILABLE, "a"), 0)
    event = grants.take(grant(Grant.AVAILABLE, "b"), 0)
    assert event is not None
    assert event.text == "qos: the network's grant at site b is available"
    assert grants.reported(0) is Grant.AVAILABLE  # path b has priority: not denied
    grants.take(grant(Grant.UNAVAILABLE, "b"), 100 * MS)
    assert grants.reported(100 * MS) is Grant.UNAVAILABLE  # both deny
    grants.take(grant(Grant.REQUESTED, "a"), 200 * MS)
    assert grants.reported(200 * MS) is Grant.REQUESTED
    grants.take(grant(Grant.UNAVAILABLE, "b"), 300 * MS)
    # site a's agent goes quiet (its site was killed): site b's word alone counts
    assert grants.reported(1_250 * MS) is Grant.UNAVAILABLE
    assert grants.agent_heard(1_250 * MS)


def test_grants_beyond_the_sites_a_drone_can_have_are_ignored() -> None:
    grants = SiteGrants(agent_timeout_ns=1_000 * MS)
    for i in range(MAX_SITES):
        grants.take(grant(Grant.UNAVAILABLE, f"s{i}"), 0)
    assert grants.take(grant(Grant.AVAILABLE, "one-too-many"), 0) is None
    assert grants.reported(0) is Grant.UNAVAILABLE
    assert len(grants.last) == MAX_SITES


def test_each_path_asks_its_own_sites_agent_and_carries_the_rest_as_it_is() -> None:
    request = QosRequest(uav="uav1", seq=3, stamp_ns=1, want=True)
    sites = {"lte": "munich", "5g": ""}
    assert as_carried(request, "lte", sites).site == "munich"  # the site its router belongs to
    assert as_carried(request, "b", {"b": "b"}).site == "b"
    assert as_carried(request, "", {}) == request  # one path: the wire as it was
    status = grant(Grant.AVAILABLE)
    assert as_carried(status, "lte", sites) is status
