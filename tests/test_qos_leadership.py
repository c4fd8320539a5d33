"""Which QoS agent is active (edge/qos/leadership.py), driven by hand with the time passed in."""

from __future__ import annotations

import pytest

from dynqos.edge.qos.leadership import RANK_KEY, TRANSITIONS, AgentRole, Guard, Leadership
from dynqos.edge.replicas import MAX_REPLICAS, ranked

SETTLE = 500


def agents(*names: str, now: int = 0) -> dict[str, Leadership]:
    """One Leadership per agent, each told of the others' member tokens."""
    out = {name: Leadership(name, now_ns=now, settle_ns=SETTLE) for name in names}
    for lead in out.values():
        for other in names:
            lead.member(other, True)
    return out


def first_and_second(*names: str) -> tuple[str, str]:
    order = ranked(RANK_KEY, names)
    return order[0], order[1]


def test_a_lone_agent_takes_over_only_once_it_has_settled() -> None:
    lead = Leadership("a", now_ns=0, settle_ns=SETTLE)
    assert lead.decide(SETTLE - 1) is None
    assert lead.next_deadline_ns(0) == SETTLE
    change = lead.decide(SETTLE)
    assert change is not None
    assert change.role is AgentRole.ACTIVE
    assert lead.is_active
    assert lead.takeovers == 1
    assert lead.decide(SETTLE + 1) is None  # stays
    assert lead.next_deadline_ns(SETTLE) is None


def test_of_agents_starting_together_only_the_first_ranked_takes_over() -> None:
    group = agents("qos", "qos-1", "qos-2")
    decided = {name: lead.decide(SETTLE) for name, lead in group.items()}
    active = [name for name, change in decided.items() if change is not None]
    assert active == [ranked(RANK_KEY, group)[0]]
    assert all(change is None or change.role is AgentRole.ACTIVE for change in decided.values())


def test_a_standby_takes_over_when_the_active_agent_goes_and_not_before() -> None:
    first, second = first_and_second("a", "b")
    group = agents("a", "b")
    assert group[first].decide(SETTLE) is not None
    standby = group[second]
    standby.active(first, True)
    assert standby.decide(SETTLE) is None
    assert not standby.is_active
    standby.active(first, False)  # its active token and its member token go together
    standby.member(first, False)
    change = standby.decide(SETTLE + 10)
    assert change is not None
    assert change.role is AgentRole.ACTIVE
    assert "no agent is active" in change.reason


def test_the_active_token_gone_before_the_member_token_waits_for_the_first_ranked() -> None:
    first, second = first_and_second("a", "b")
    standby = agents("a", "b")[second]
    standby.active(first, True)
    standby.active(first, False)
    assert standby.decide(SETTLE) is None  # `first` still lives and ranks first: it is its turn
    standby.member(first, False)
    assert standby.decide(SETTLE) is not None


def test_a_new_agent_never_displaces_the_active_one_even_when_it_ranks_first() -> None:
    # the incumbent ranks second of the two; the newcomer, first, sees it active and stands by
    first, second = first_and_second("a", "b")
    incumbent = Leadership(second, now_ns=0, settle_ns=SETTLE)
    assert incumbent.decide(SETTLE) is not None
    newcomer = Leadership(first, now_ns=SETTLE, settle_ns=SETTLE)
    newcomer.member(second, True)
    newcomer.active(second, True)
    incumbent.member(first, True)
    assert newcomer.decide(3 * SETTLE) is None
    assert not newcomer.is_active
    assert incumbent.decide(3 * SETTLE) is None
    assert incumbent.is_active


def test_two_active_agents_settle_by_rank_and_the_other_steps_down() -> None:
    first, second = first_and_second("a", "b")
    group = {name: Leadership(name, now_ns=0, settle_ns=SETTLE) for name in ("a", "b")}
    for lead in group.values():  # a partition: each saw only itself
        assert lead.decide(SETTLE) is not None
    for name, lead in group.items():  # healed: each sees the other's tokens
        other = second if name == first else first
        lead.member(other, True)
        lead.active(other, True)
    assert group[first].decide(SETTLE + 1) is None
    assert group[first].is_active
    change = group[second].decide(SETTLE + 1)
    assert change is not None
    assert change.role is AgentRole.STANDBY
    assert first in change.reason
    assert not group[second].is_active


def test_own_tokens_invalid_names_and_a_flood_are_not_counted_as_peers() -> None:
    lead = Leadership("a", now_ns=0, settle_ns=SETTLE)
    assert not lead.member("a", True)
    assert not lead.active("a", True)
    assert not lead.member("bad/name", True)
    assert not lead.member("x" * 65, True)
    for i in range(MAX_REPLICAS + 10):
        lead.member(f"flood{i}", True)
    assert len(lead.members) == MAX_REPLICAS
    assert lead.refused == 2 + 11
    assert not lead.member("never-seen", False)  # a departure of a stranger changes nothing


def test_an_invalid_own_id_is_refused() -> None:
    with pytest.raises(ValueError, match="invalid"):
        Leadership("no spaces", now_ns=0, settle_ns=SETTLE)


def test_each_row_of_the_role_table_with_its_guard_held_and_not() -> None:
    """TRANSITIONS, row by row: the guard not yet held changes nothing, held it gives the row's role."""
    assert set(TRANSITIONS) == {(AgentRole.STANDBY, Guard.TAKE_OVER), (AgentRole.ACTIVE, Guard.STEP_DOWN)}
    first, second = first_and_second("a", "b")
    # STANDBY --TAKE_OVER--> ACTIVE: no active token, settled, ranked first among the members
    group = agents("a", "b")
    assert group[second].decide(SETTLE) is None  # settled, no active token, but not ranked first
    assert group[first].decide(SETTLE - 1) is None  # ranked first, not settled
    group[first].active(second, True)
    assert group[first].decide(SETTLE) is None  # another holds the active token
    group[first].active(second, False)
    change = group[first].decide(SETTLE)
    assert change is not None
    assert (change.role, group[first].role) == (AgentRole.ACTIVE, AgentRole.ACTIVE)
    # ACTIVE --STEP_DOWN--> STANDBY: another active agent that ranks first
    lead = Leadership(second, now_ns=0, settle_ns=SETTLE)
    assert lead.decide(SETTLE) is not None  # alone, it took over
    lead.active(f"{second}-lower", True)
    if ranked(RANK_KEY, [second, f"{second}-lower"])[0] == second:
        assert lead.decide(SETTLE + 1) is None  # one that ranks below: it stays
    lead.active(first, True)
    change = lead.decide(SETTLE + 2)
    assert change is not None
    assert (change.role, lead.role) == (AgentRole.STANDBY, AgentRole.STANDBY)
    assert first in change.reason
