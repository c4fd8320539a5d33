"""What the QoS agent does for one drone, as pure logic with the time passed in.

The drone decides when it wants its priority flow and switches its zenoh link at once; this follows it
with the network (docs/qos.md). Per drone there is at most one QoD session. `next_op` says which API
call is due now (create, poll, extend, delete, or none), the shell makes it and reports the outcome
back; `grant` is what the drone is told. Rules a user relies on live here, each in one place:

- a release waits until the drone has been out of priority for the hold-down time, so a flapping link
  does not churn sessions;
- a session is extended before it expires while priority is still wanted;
- an operator may cap a session at its profile's maximum duration (an extend then answers 200 with the
  same `expiresAt`): a session whose expiry an extend did not move is not extended again, but replaced
  shortly before it ends (delete, then create: CAMARA answers 409 to a second session for one device);
  a session that ends by DURATION_EXPIRED is asked for again at once, not after a back-off;
- a session the network ended (UNAVAILABLE) is deleted at once (the API wants its resources released
  before another is created) and asked for again after a back-off while still wanted;
- a refusal (400/403/404/422) or an API that keeps failing (429, 5xx, timeouts) is a grant of
  UNAVAILABLE with the reason, and the next attempt waits, doubling up to 8x;
- an answer that says the agent's own settings are wrong (an identifier the operator will not take, a
  duration out of the profile's range, a profile it does not offer, credentials without the scope) is
  not asked again: the drone is told UNAVAILABLE with the setting to fix, for as long as the agent runs;
- while the operator's QoS Profiles API says the profile cannot start a session (withdrawn, INACTIVE),
  no session is created and a wanting drone is told UNAVAILABLE with that reason; a session it holds
  runs on; once the profile is ACTIVE again the drone asks at once;
- an operator's Retry-After is honoured up to `RETRY_AFTER_CEILING_NS`;
- a drone the arbiter does not admit (policy "arbiter", edge/qos/arbiter.py) is told UNAVAILABLE with the
  arbiter's reason, and a session it holds is deleted at once: a revocation frees the budget now.

With backend "nef" the session is a NEF subscription (edge/qos/nef_calls.py maps its events onto these
statuses): it has no end to extend, so EXTEND and RENEW never come due, and a read only finds it gone.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from dynqos.common.clock import NS_PER_S, to_ns
from dynqos.common.config import CamaraConfig, QosConfig
from dynqos.common.modes import Grant

MAX_BACKOFF_FACTOR = 8
# The longest Retry-After the agent honours: ten minutes is a third of a typical flight's battery; an
# HTTP-date further out (a clock off, a bad header) must not silence the agent for the rest of the flight.
RETRY_AFTER_CEILING_NS = 600 * NS_PER_S
RETRY_DELETE_NS = NS_PER_S  # a failed delete (or extend) is tried again after this
# An extend that moved the session's end by less than this did not extend it (the operator capped it).
# expiresAt comes on the operator's wall clock and is read against ours: a second absorbs the skew.
CAPPED_TOLERANCE_NS = NS_PER_S


class Op(enum.Enum):
    CREATE = "create"
    POLL = "poll"
    EXTEND = "extend"
    RENEW = "renew"  # replace a capped session: delete it, create its successor
    DELETE = "delete"


class QodStatus(str, enum.Enum):
    """CAMARA `qosStatus`."""

    REQUESTED = "REQUESTED"
    AVAILABLE = "AVAILABLE"
    UNAVAILABLE = "UNAVAILABLE"


class SessionState(enum.Enum):
    """The drone's session as the agent knows it. The operator moves it (its answers to create, poll,
    extend and delete, and its notifications: `observed`, `extended`, `deleted`); what the agent decides
    is the call each state calls for, `OPS`."""

    NONE = "none"  # no session: created when priority is wanted
    REQUESTED = "requested"  # created; the network has not decided
    AVAILABLE = "available"  # the priority flow has its weight
    CAPPED = "capped"  # available, but an extend did not move its end: replaced shortly before it ends
    ENDED = "ended"  # the network ended it (UNAVAILABLE): deleted at once


class Need(enum.Enum):
    """What a row of `OPS` asks of the drone's want, the arbiter, the settings and the clock."""

    CREATE_DUE = "wanted and admitted; no refused setting, no withdrawn profile; the back-off is over"
    GO_DUE = "ended, revoked by the arbiter, or unwanted for the hold-down; no failed delete waiting"
    GO_WAIT = "to be deleted, and a failed delete waits its retry time: nothing else until then"
    READ_DUE = "the poll interval is over, or the session's end has passed"
    RENEW_DUE = "wanted, within renew_before_s of its end; no failed renewal waiting"
    EXTEND_DUE = "wanted, within extend_before_s of its end; no failed extend waiting"


_HELD = frozenset({SessionState.REQUESTED, SessionState.AVAILABLE, SessionState.CAPPED, SessionState.ENDED})

# The call due now: the first row whose state matches and whose need holds (None: wait). An enum and a
# table, as the drone's take-off and the agents' leadership have: six rows do not need a library.
OPS: tuple[tuple[frozenset[SessionState], Need, Op | None], ...] = (
    (frozenset({SessionState.NONE}), Need.CREATE_DUE, Op.CREATE),
    (_HELD, Need.GO_DUE, Op.DELETE),
    (_HELD, Need.GO_WAIT, None),
    (_HELD, Need.READ_DUE, Op.POLL),
    (frozenset({SessionState.CAPPED}), Need.RENEW_DUE, Op.RENEW),
    (frozenset({SessionState.AVAILABLE}), Need.EXTEND_DUE, Op.EXTEND),
)


@dataclass(frozen=True, slots=True)
class Session:
    """What the API last said of the drone's session; `expires_ns` on the agent's monotonic clock."""

    session_id: str
    status: QodStatus
    status_info: str = ""
    expires_ns: int | None = None


class DroneGrant:
    """One drone's want, its session and what it is told."""

    def __init__(self, uav: str, config: QosConfig, now_ns: int) -> None:
        self.uav = uav
        self.asks = config.backend != "links"  # the network is asked (links: its static policy holds)
        self._timeout_ns = to_ns(config.drone_timeout_s)
        self._hold_down_ns = to_ns(config.hold_down_s)
        if config.backend == "nef":  # a read says only that the subscription is there: its news is notified
            self._poll_ns = self._watch_ns = to_ns(config.nef.read_interval_s)
        else:
            self._poll_ns = to_ns(config.camara.poll_interval_s)
            self._watch_ns = max(self._poll_ns, NS_PER_S)
        self._extend_ns = to_ns(config.camara.extend_before_s)
        self._renew_ns = to_ns(config.camara.renew_before_s)
        self.capped = ""  # the session whose end an extend could not move: replaced, not extended
        retry_s = (
            config.nef.retry_after_denied_s if config.backend == "nef" else config.camara.retry_after_denied_s
        )
        self._retry_ns = to_ns(retry_s)
        self.wanted = False
        self.heard_ns = now_ns
        self.request_seq = 0
        self.session: Session | None = None
        self.reason = ""
        self.refused = False  # the last attempt was refused or failed: UNAVAILABLE until the next succeeds
        self.misconfigured = ""  # the operator refused our settings: never asked again (the reason)
        self.withdrawn = ""  # the profile cannot start a session now (the reason): no create until it can
        self._unwanted_since_ns: int | None = now_ns
        self._retry_at_ns = 0
        self._failures = 0
        self._next_read_ns = 0
        self._next_extend_ns = 0
        self._next_delete_ns = 0
        self.admitted = True  # the arbiter lets it hold priority (always, with policy "grant-all")
        self.arbiter_reason = ""

    # ---- what the arbiter says --------------------------------------------------------------------------

    def admit(self, admitted: bool, reason: str) -> None:
        self.admitted = admitted
        self.arbiter_reason = "" if admitted else reason

    def why(self) -> str:
        """The reason the drone is told with its grant."""
        return self.reason if self.admitted else self.arbiter_reason

    def lingering(self, now_ns: int) -> bool:
        """It no longer wants priority but still holds its session (the hold-down)."""
        return self.session is not None and not self.wants(now_ns) and self.admitted

    # ---- what the drone says ----------------------------------------------------------------------------

    def request(self, want: bool, seq: int, now_ns: int) -> None:
        self.heard_ns = now_ns
        self.request_seq = max(self.request_seq, seq)
        if want and not self.wanted and not self.misconfigured:  # a new episode: asks at once
            self._failures = 0
            self._retry_at_ns = 0
            self.refused, self.reason = (True, self.withdrawn) if self.withdrawn else (False, "")
        if want:
            self._unwanted_since_ns = None
        elif self._unwanted_since_ns is None:
            self._unwanted_since_ns = now_ns
        self.wanted = want

    def wants(self, now_ns: int) -> bool:
        """Priority is wanted: the drone said so and has been heard within the drone timeout."""
        return self.wanted and now_ns - self.heard_ns <= self._timeout_ns

    def silent(self, now_ns: int) -> bool:
        return now_ns - self.heard_ns > self._timeout_ns

    def _track(self, now_ns: int) -> bool:
        wants = self.wants(now_ns)
        if wants:
            self._unwanted_since_ns = None
        elif self._unwanted_since_ns is None:  # it went silent: unwanted since its timeout ran out
            self._unwanted_since_ns = self.heard_ns + self._timeout_ns if self.wanted else now_ns
        return wants

    # ---- what to do -------------------------------------------------------------------------------------

    @property
    def state(self) -> SessionState:
        s = self.session
        if s is None:
            return SessionState.NONE
        if s.status is QodStatus.UNAVAILABLE:
            return SessionState.ENDED
        if s.status is QodStatus.REQUESTED:
            return SessionState.REQUESTED
        return SessionState.CAPPED if s.session_id == self.capped else SessionState.AVAILABLE

    def next_op(self, now_ns: int) -> Op | None:
        """The call due now (`OPS`); None: none."""
        wants = self._track(now_ns) and self.admitted
        if not self.asks:
            return None
        state = self.state
        for states, need, op in OPS:
            if state in states and self._holds(need, wants, now_ns):
                return op
        return None

    def _holds(self, need: Need, wants: bool, now_ns: int) -> bool:
        s = self.session
        if need is Need.CREATE_DUE:
            return wants and now_ns >= self._retry_at_ns and not self.misconfigured and not self.withdrawn
        assert s is not None  # every other row is a held session's
        if need in (Need.GO_DUE, Need.GO_WAIT):
            to_go = (
                s.status is QodStatus.UNAVAILABLE
                or not self.admitted
                or (not wants and self._released(now_ns))
            )
            return to_go and (now_ns >= self._next_delete_ns) == (need is Need.GO_DUE)
        if need is Need.READ_DUE:
            return now_ns >= self._next_read_ns or (s.expires_ns is not None and now_ns >= s.expires_ns)
        if not wants or s.expires_ns is None:
            return False
        left = s.expires_ns - now_ns
        if need is Need.RENEW_DUE:
            return left <= self._renew_ns and now_ns >= self._next_delete_ns
        return left <= self._extend_ns and now_ns >= self._next_extend_ns  # EXTEND_DUE

    def _released(self, now_ns: int) -> bool:
        since = self._unwanted_since_ns
        return since is not None and now_ns - since >= self._hold_down_ns

    def next_deadline_ns(self, now_ns: int) -> int:
        """When `next_op` may next change without news from the drone or the API (the shell sleeps until
        then, or until the drone speaks)."""
        candidates = [self.heard_ns + self._timeout_ns + 1]
        if self._unwanted_since_ns is not None:
            candidates.append(self._unwanted_since_ns + self._hold_down_ns)
        if self.session is None:
            candidates.append(self._retry_at_ns)
        else:
            candidates += [self._next_read_ns, self._next_delete_ns, self._next_extend_ns]
            if self.session.expires_ns is not None:
                lead = self._renew_ns if self.session.session_id == self.capped else self._extend_ns
                candidates += [self.session.expires_ns - lead, self.session.expires_ns]
        future = [c for c in candidates if c > now_ns]
        return min(future) if future else now_ns + self._watch_ns

    def grant(self, now_ns: int) -> Grant:
        if not self.admitted:
            return Grant.UNAVAILABLE if self.wants(now_ns) or self.session is not None else Grant.NONE
        if not self.asks:
            return Grant.AVAILABLE if self.wants(now_ns) else Grant.NONE
        s = self.session
        if s is not None and s.status is QodStatus.AVAILABLE:
            return Grant.AVAILABLE
        if self.refused or (s is not None and s.status is QodStatus.UNAVAILABLE):
            return Grant.UNAVAILABLE if self.wants(now_ns) or s is not None else Grant.NONE
        if s is not None or self.wants(now_ns):
            return Grant.REQUESTED
        return Grant.NONE

    # ---- what the API answered --------------------------------------------------------------------------

    def observed(self, session: Session, now_ns: int) -> None:
        """A SessionInfo from create, get, extend or a notification."""
        before = self.session
        self.session = session
        settled = session.status is not QodStatus.REQUESTED
        self._next_read_ns = now_ns + (self._watch_ns if settled else self._poll_ns)
        if session.status is QodStatus.AVAILABLE:
            self.refused, self.reason, self._failures = False, "", 0
        elif session.status is QodStatus.UNAVAILABLE and session.status_info == "DURATION_EXPIRED":
            self.reason = "the session reached its duration"  # deleted, then asked for again at once
        elif session.status is QodStatus.UNAVAILABLE:
            self.refused = True
            self.reason = f"the network ended the session ({session.status_info or 'no reason given'})"
            if before is None or before.status is not QodStatus.UNAVAILABLE:
                self._back_off(now_ns)

    def extended(self, session: Session, now_ns: int) -> bool:
        """The answer to an extend; True when the operator capped the session (its end did not move), so
        that it is replaced before it ends instead of extended again."""
        before = self.session
        capped = (
            before is not None
            and before.session_id == session.session_id
            and before.expires_ns is not None
            and session.expires_ns is not None
            and session.expires_ns < before.expires_ns + CAPPED_TOLERANCE_NS
        )
        if capped:
            self.capped = session.session_id
        self.observed(session, now_ns)
        return capped

    def read_now(self) -> None:
        """News of the session (a notification): read it at the next chance."""
        self._next_read_ns = 0

    def deleted(self, now_ns: int) -> None:
        """The session is gone (deleted by us, or 404: not there any more)."""
        self.session = None
        self.capped = ""
        self._next_delete_ns = 0
        if self.withdrawn and not self.misconfigured:
            self.refused, self.reason = True, self.withdrawn
        elif not self.wants(now_ns) and not self.misconfigured:
            self.refused, self.reason = False, ""

    def handed_over(self) -> None:
        """Whatever this agent knew of the session is not its own any more (another agent holds the
        sessions) or is about to be replaced by what the operator says (this one took over)."""
        self.session = None
        self.capped = ""
        self._next_read_ns = self._next_extend_ns = self._next_delete_ns = 0

    def denied(self, reason: str, now_ns: int, retry_after_ns: int = 0) -> None:
        """The operator refused (400/403/404/422): no session; ask again after the back-off (or the
        operator's Retry-After, up to the ceiling, when it is longer)."""
        self.refused, self.reason = True, reason
        self._back_off(now_ns)
        self._retry_at_ns = max(self._retry_at_ns, now_ns + min(retry_after_ns, RETRY_AFTER_CEILING_NS))

    def profile_withdrawn(self, reason: str) -> None:
        """What the operator's QoS Profiles API says of the profile now: `reason` why it cannot start a
        session ("" = it can again, and a wanting drone asks at once)."""
        was, self.withdrawn = self.withdrawn, reason
        if self.misconfigured or reason == was:
            return
        if reason and self.session is None:
            self.refused, self.reason = True, reason
        elif not reason:
            self._failures, self._retry_at_ns = 0, 0
            if self.session is None:
                self.refused, self.reason = False, ""

    def retime(self, camara: CamaraConfig) -> None:
        """The margins of settings fitted to the operator's profile (a shorter maxDuration shrinks them)."""
        self._extend_ns = to_ns(camara.extend_before_s)
        self._renew_ns = to_ns(camara.renew_before_s)

    def refused_settings(self, reason: str) -> None:
        """The operator refused the agent's own settings for this drone: never asked again."""
        self.refused, self.reason, self.misconfigured = True, reason, reason

    def failed(self, op: Op, reason: str, now_ns: int, retry_after_ns: int = 0) -> None:
        """The call did not get an answer (timeouts, 429 or 5xx after the client's retries); with a
        Retry-After the call is not tried before it (up to the ceiling)."""
        after = now_ns + max(RETRY_DELETE_NS, min(retry_after_ns, RETRY_AFTER_CEILING_NS))
        if op is Op.CREATE:
            self.denied(reason, now_ns, retry_after_ns)
        elif op in (Op.DELETE, Op.RENEW):  # a failed renewal: the session stays, and ends on its own
            self._next_delete_ns = after
        elif op is Op.EXTEND:
            self._next_extend_ns = after
        else:
            self._next_read_ns = now_ns + max(self._watch_ns, min(retry_after_ns, RETRY_AFTER_CEILING_NS))

    def _back_off(self, now_ns: int) -> None:
        factor = min(MAX_BACKOFF_FACTOR, 2**self._failures)
        self._failures += 1
        self._retry_at_ns = now_ns + self._retry_ns * factor
