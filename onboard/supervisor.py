"""The paper's probabilistic finite state machine (PFSM), as pure logic with time passed in.

It decides, every tick, which QoS flow the drone uses, how fast the camera streams and whether the
edge or the onboard fallback flies the drone, from three signals:

- latency: P_lat = w1 P_cam(t1) + w2 P_cc(t2), where t1 and t2 are sliding-window means of camera
  latency and C&C RTT and P(t) = 1 / (1 + exp(mu (rho - t))) (paper eq. 1-3). HL when
  P_lat > th_lat, LL otherwise, NA while there is no evidence at all;
- risk: the filtered spaciousness s_k = a s_{k-1} + b S_k; HR at or below 3 m, MR up to 5 m, LR
  above; NA before the first depth sample (treated as MR: priority rather than throttling), and NA
  again when depth has stopped for `risk_stale_s` (a camera gone, a recording ended), then read as
  HR: a drone that has lost sight of its surroundings keeps its control traffic on the priority
  flow and is not throttled; the filter starts again from the first sample when depth returns;
- the command watchdog, which sends any state to qA at once (the one transition allowed outside
  Table I).

Only the transitions of the paper's Table I are possible; dwell, persistence and recovery timers
keep noise from making the machine flap. See docs/supervisor.md for every guard.
"""

from __future__ import annotations

import enum
import math
import random
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from dynqos.common.clock import NS_PER_S
from dynqos.common.config import SupervisorConfig
from dynqos.common.modes import ControlSource, Flow, SupervisorState
from dynqos.common.stats import Ema, SlidingWindow

TRANSITION_LOG_SIZE = 1000


State = SupervisorState


Q1, Q2, Q3, Q4, Q5, Q6, QA = State

# Table I of the paper: the only successors of each state.
TABLE_I: dict[State, frozenset[State]] = {
    Q1: frozenset({Q1, Q2, Q3, Q4}),
    Q2: frozenset({Q1, Q2, Q5}),
    Q3: frozenset({Q1, Q3, Q5, Q6}),
    Q4: frozenset({Q1, Q4, Q6, QA}),
    Q5: frozenset({Q5, Q1, QA}),
    Q6: frozenset({Q6, Q1, QA}),
    QA: frozenset({QA, Q1}),
}
WATCHDOG_CAUSE = "watchdog"


class Latency(str, enum.Enum):
    LL = "LL"
    HL = "HL"
    NA = "NA"


class Risk(str, enum.Enum):
    LR = "LR"
    MR = "MR"
    HR = "HR"
    NA = "NA"


@dataclass(frozen=True, slots=True)
class Actions:
    flow: Flow  # the state's flow: the drone's state (and status) travel on it
    camera_rate_factor: float  # fraction of the nominal camera frame rate
    control_source: ControlSource  # EDGE or FALLBACK: what the supervisor wants
    camera_flow: Flow  # the camera's flow; it differs from `flow` while probing the default flow


RATE_ADAPTATION_STATES = frozenset({Q4, Q5, Q6})
PRIORITY_STATES = frozenset({Q2, Q3, Q5, Q6})


@dataclass(frozen=True, slots=True, kw_only=True)
class Inputs:
    """What the daemon measured since the last tick.

    `*_outstanding_ms` is the age of the oldest request still unanswered (a camera frame with no
    ack, a state with no command), a lower bound on the next sample: when acks stop, the window
    mean alone would keep reporting the last good latency.
    """

    camera_latencies_ms: Sequence[float] = ()
    cc_rtts_ms: Sequence[float] = ()
    camera_outstanding_ms: float | None = None
    cc_outstanding_ms: float | None = None
    spaciousness_m: float | None = None
    watchdog_expired: bool = False
    # The network refused the priority flow (the QoS agent's grant is UNAVAILABLE): on the priority
    # flow HL is then the paper's "priority applied but the delay still rises" at once.
    priority_denied: bool = False
    sinr_db: float | None = None  # the modem's SINR, fresh (None: no modem or no reading)
    # the 5G core's own measurement of the priority flow's round trip (NEF QoS monitoring), fresh
    network_rtt_ms: float | None = None


@dataclass(frozen=True, slots=True)
class Transition:
    stamp_ns: int
    source: State
    target: State
    cause: str
    p_lat: float | None
    p_cs: float | None


@dataclass(frozen=True, slots=True)
class Signals:
    latency: Latency
    risk: Risk
    watchdog: bool
    t_cam_ms: float | None
    t_cc_ms: float | None
    spaciousness_m: float | None
    p_cam: float | None
    p_cc: float | None
    p_lat: float | None
    p_cs: float | None
    priority_denied: bool = False
    depth_lost: bool = False  # depth stopped for risk_stale_s: risk NA, read as HR


@dataclass(frozen=True, slots=True)
class Decision:
    state: State
    actions: Actions
    signals: Signals
    transition: Transition | None
    note: str = ""  # what happened this tick that is not a transition (a probe started or failed)


def sigmoid(t: float, mu: float, rho: float) -> float:
    """P(t) = 1 / (1 + exp(mu (rho - t))), safe for any finite or infinite input."""
    if math.isnan(t):
        raise ValueError("P(t) of NaN")
    z = mu * (rho - t)
    if z >= 0:
        e = math.exp(-z) if z < 745 else 0.0
        return e / (1.0 + e)
    return 1.0 / (1.0 + math.exp(z))


def _effective(window: SlidingWindow, outstanding_ms: float | None) -> float | None:
    """The window mean, with an unanswered request counted as one more sample of at least its age.

    One late answer then moves the mean by a sample's worth, as it would once it arrives, while a
    silent link (an age growing to seconds) soon dominates it; the mean alone would keep reporting the
    last good latency forever.
    """
    mean = window.mean()
    if outstanding_ms is None or not math.isfinite(outstanding_ms) or outstanding_ms < 0:
        return mean
    if mean is None:
        return outstanding_ms
    if outstanding_ms <= mean:
        return mean
    n = len(window)
    return (mean * n + outstanding_ms) / (n + 1)


def _fast_mean(window: SlidingWindow, n: int, outstanding_ms: float | None) -> float:
    """Mean of the newest n samples, the newest replaced by the outstanding age when that is larger.

    This is t2's fast attack: a queue building up raises it within a few samples (and the age of the
    state still unanswered raises it one RTT sooner), where the 50-sample mean takes a second. Less than
    n samples: 0, no evidence yet.
    """
    recent = window.last(n)
    if len(recent) < n:
        return 0.0
    if outstanding_ms is not None and math.isfinite(outstanding_ms) and outstanding_ms > recent[-1]:
        recent[0:1] = []
        recent.append(outstanding_ms)
    return math.fsum(recent) / n


@dataclass(frozen=True, slots=True)
class _Firing:
    """What the signals say this step, read once for every row of Table I."""

    risk: Risk  # NA (no depth yet) is read as MR
    hl: bool
    react: bool  # HL has held for persist_s: the first reaction from q1
    escalate: bool  # HL has held for escalate_s: the next step up
    recover: bool  # LL has held for the recovery time
    persists: str  # the cause an escalation gives


class Supervisor:
    """The PFSM. `step` once per tick with the inputs gathered since the previous tick."""

    def __init__(self, config: SupervisorConfig, start_ns: int = 0) -> None:
        self.config = config
        self._cam = SlidingWindow(config.window[0])
        self._cc = SlidingWindow(config.window[1])
        self._risk = Ema(config.risk_a, config.risk_b)
        self._depth_ns: int | None = None  # the newest depth sample's tick
        self._rng = random.Random(config.seed)
        self._stochastic = config.mode == "stochastic"
        self.state = Q1
        self._entered_ns = start_ns
        self._hl_since_ns: int | None = None
        self._ll_since_ns: int | None = None
        self._rate = 1.0
        self._rate_changed_ns = start_ns
        self._min_rate_since_ns: int | None = None
        self._recover_ns = self._ns(config.recover_s)
        self._last_recovery_ns: int | None = None
        self._probe_since_ns: int | None = None
        self._probe_wait_ns = self._recover_ns  # after a failed probe, the next waits this long...
        self._probe_not_before_ns = start_ns  # ...from here
        self._note = ""
        self.log: deque[Transition] = deque(maxlen=TRANSITION_LOG_SIZE)

    @staticmethod
    def _ns(seconds: float) -> int:
        return round(seconds * NS_PER_S)

    def camera_flow(self, state_flow: Flow) -> Flow:
        """The camera's flow beside the state's: the same, or the default flow it is pinned to."""
        return Flow.DEFAULT if self.config.camera_flow == "default" else state_flow

    def actions(self) -> Actions:
        state = self.state
        if state is QA:
            camera = self.camera_flow(Flow.PRIORITY)
            return Actions(Flow.PRIORITY, self.config.min_rate_factor, ControlSource.FALLBACK, camera)
        if self._probe_since_ns is not None:  # the camera tries the default flow at q1's rate
            return Actions(Flow.PRIORITY, 1.0, ControlSource.EDGE, Flow.DEFAULT)
        flow = Flow.PRIORITY if state in PRIORITY_STATES else Flow.DEFAULT
        rate = self._rate if state in RATE_ADAPTATION_STATES else 1.0
        return Actions(flow, rate, ControlSource.EDGE, self.camera_flow(flow))

    def _signals(self, inputs: Inputs, now_ns: int) -> Signals:
        cfg = self.config
        for sample in inputs.camera_latencies_ms:
            if math.isfinite(sample) and sample >= 0:
                self._cam.push(sample)
        for sample in inputs.cc_rtts_ms:
            if math.isfinite(sample) and sample >= 0:
                self._cc.push(sample)
        if inputs.spaciousness_m is not None and math.isfinite(inputs.spaciousness_m):
            self._risk.update(max(0.0, inputs.spaciousness_m))
            self._depth_ns = now_ns
        depth_lost = self._depth_ns is not None and now_ns - self._depth_ns > self._ns(cfg.risk_stale_s)
        if depth_lost:
            self._risk = Ema(cfg.risk_a, cfg.risk_b)  # what it held no longer describes the space

        t_cam = _effective(self._cam, inputs.camera_outstanding_ms)
        t_cc = _effective(self._cc, inputs.cc_outstanding_ms)
        if t_cc is not None and cfg.cc_fast_window:
            t_cc = max(t_cc, _fast_mean(self._cc, cfg.cc_fast_window, inputs.cc_outstanding_ms))
        p_cam = None if t_cam is None else sigmoid(t_cam, cfg.mu[0], cfg.rho[0])
        p_cc = None if t_cc is None else sigmoid(t_cc, cfg.mu[1], cfg.rho[1])
        terms = [(w, p) for w, p in zip(cfg.w, (p_cam, p_cc), strict=True) if p is not None]
        weight = sum(w for w, _ in terms)
        # A missing term is left out and the rest re-weighted; no evidence at all is NA, not LL.
        p_lat = sum(w * p for w, p in terms) / weight if terms and weight > 0 else None
        if cfg.radio_aware and inputs.sinr_db is not None and math.isfinite(inputs.sinr_db):
            p_radio = 1.0 - sigmoid(inputs.sinr_db, cfg.radio_mu, cfg.radio_sinr_db)  # the link is fading
            p_lat = p_radio if p_lat is None else max(p_lat, p_radio)
        if cfg.network_aware and inputs.network_rtt_ms is not None and math.isfinite(inputs.network_rtt_ms):
            p_net = sigmoid(inputs.network_rtt_ms, cfg.mu[1], cfg.rho[1])  # read as a C&C RTT (eq. 1)
            p_lat = p_net if p_lat is None else max(p_lat, p_net)
        latency = Latency.NA if p_lat is None else (Latency.HL if p_lat > cfg.th_lat else Latency.LL)

        s_k = self._risk.value
        if s_k is None:
            risk, p_cs = Risk.NA, None
        else:
            risk = Risk.HR if s_k <= cfg.risk_high_m else Risk.MR if s_k <= cfg.risk_medium_m else Risk.LR
            p_cs = 1.0 - sigmoid(s_k, cfg.mu[2], cfg.rho[2])  # rises as the space closes in
        return Signals(
            latency,
            risk,
            inputs.watchdog_expired,
            t_cam,
            t_cc,
            s_k,
            p_cam,
            p_cc,
            p_lat,
            p_cs,
            inputs.priority_denied,
            depth_lost,
        )

    def _update_timers(self, signals: Signals, now_ns: int) -> None:
        if signals.latency is Latency.HL:
            self._ll_since_ns = None
            if self._hl_since_ns is None:
                self._hl_since_ns = now_ns
        elif signals.latency is Latency.LL:
            self._hl_since_ns = None
            if self._ll_since_ns is None:
                self._ll_since_ns = now_ns
        else:
            self._hl_since_ns = self._ll_since_ns = None

    @staticmethod
    def _held(since_ns: int | None, now_ns: int, need_ns: int) -> bool:
        return since_ns is not None and now_ns - since_ns >= need_ns

    def _fires(self, held: bool, instant: bool, probability: float | None) -> bool:
        """Deterministic mode: the condition held long enough. Stochastic mode: the condition holds
        now and a draw with the signal's probability succeeds (repeated draws replace persistence)."""
        if not self._stochastic:
            return held
        return instant and self._rng.random() < (probability if probability is not None else 1.0)

    def _adapt_rate(self, signals: Signals, now_ns: int) -> None:
        cfg = self.config
        if self.state not in RATE_ADAPTATION_STATES or signals.latency is not Latency.HL:
            return
        if self._rate > cfg.min_rate_factor and now_ns - self._rate_changed_ns >= self._ns(cfg.rate_step_s):
            self._rate = max(cfg.min_rate_factor, self._rate / 2.0)
            self._rate_changed_ns = now_ns
            if self._rate == cfg.min_rate_factor:
                self._min_rate_since_ns = now_ns

    def _choose(self, signals: Signals, now_ns: int) -> tuple[State, str] | None:
        """Table I: the move the signals call for from the current state (None: stay)."""
        if signals.watchdog:
            return (QA, WATCHDOG_CAUSE) if self.state is not QA else None
        if now_ns - self._entered_ns < self._ns(self.config.dwell_s):
            return None
        f = self._firing(signals, now_ns)
        state = self.state
        if state is Q1:
            return self._from_q1(signals, f)
        if state in (Q2, Q3):
            return self._from_priority(signals, f, now_ns)
        if state in RATE_ADAPTATION_STATES:
            return self._from_rate_adaptation(signals, f, now_ns)
        return (Q1, "link is back and LL holds") if f.recover else None  # qA

    def _firing(self, signals: Signals, now_ns: int) -> _Firing:
        cfg = self.config
        hl, ll = signals.latency is Latency.HL, signals.latency is Latency.LL
        p_lat = signals.p_lat
        p_ll = None if p_lat is None else 1.0 - p_lat
        # From q1 the first reaction is quick; escalating further waits until the latency window has
        # flushed the samples from before the last switch (N2 x T_mpc = 2.5 s by default).
        react = self._fires(self._held(self._hl_since_ns, now_ns, self._ns(cfg.persist_s)), hl, p_lat)
        escalate = self._fires(self._held(self._hl_since_ns, now_ns, self._ns(cfg.escalate_s)), hl, p_lat)
        persists = "HL persists on the priority flow"
        if signals.priority_denied and self.state in (Q2, Q3):
            escalate = react  # waiting for priority to help is waiting for nothing
            persists = "HL on the priority flow the network refused"
        # The anti-flap back-off is about the flows (q1 <-> q3/q4); it does not keep a drone in its
        # fallback once the link is back: qA returns after the plain recovery time.
        recover_ns = self._ns(cfg.recover_s) if self.state is QA else self._recover_ns
        return _Firing(
            risk=_read_risk(signals),
            hl=hl,
            react=react,
            escalate=escalate,
            recover=self._fires(self._held(self._ll_since_ns, now_ns, recover_ns), ll, p_ll),
            persists=persists,
        )

    def _from_q1(self, signals: Signals, f: _Firing) -> tuple[State, str] | None:
        if f.risk is Risk.HR and self._fires(True, True, signals.p_cs):
            return Q2, "HR: proactive priority"
        if f.react:
            return (Q4, "LR and HL") if f.risk is Risk.LR else (Q3, f"{f.risk.value} and HL")
        return None

    def _from_priority(self, signals: Signals, f: _Firing, now_ns: int) -> tuple[State, str] | None:
        """q2 (HR: proactive priority) and q3 (MR or HR with HL: priority flow)."""
        if f.escalate:
            return (Q5, f"{f.persists} (HR)") if self.state is Q2 or f.risk is Risk.HR else (Q6, f.persists)
        if f.risk is not Risk.HR and f.recover:
            cause = "LL holds and risk is no longer HR" if self.state is Q2 else "LL holds"
            return self._probe(signals, now_ns, cause)
        return None

    def _from_rate_adaptation(self, signals: Signals, f: _Firing, now_ns: int) -> tuple[State, str] | None:
        cfg = self.config
        at_min = self._rate <= cfg.min_rate_factor and self._min_rate_since_ns is not None
        since = None
        if at_min and self._hl_since_ns is not None:
            since = max(self._hl_since_ns, self._min_rate_since_ns or 0)
        if at_min and self._fires(self._held(since, now_ns, self._ns(cfg.escalate_s)), f.hl, signals.p_lat):
            return QA, "HL persists at the minimum camera rate"
        if self.state is Q4 and f.risk is not Risk.LR and self._fires(f.hl, f.hl, signals.p_lat):
            return Q6, f"{f.risk.value} and HL: priority flow"
        if f.recover:
            return (Q1, "LL holds") if self.state is Q4 else self._probe(signals, now_ns, "LL holds")
        return None

    def _probe(self, signals: Signals, now_ns: int, cause: str) -> tuple[State, str] | None:
        """Return to q1 only once the default flow has carried the camera, at q1's rate, for probe_s.

        Going back while the cell is still loaded would put the state behind a growing queue until HL
        is seen again. The camera is the bulk of what q1 sends, so it tests the default flow first while
        the state stays on the priority flow: if its latency passes rho1 the probe ends and the next try
        waits twice as long, and the state never saw the queue. A drone whose camera has never been
        acknowledged (no camera, no detector) has no evidence to probe with: it returns after probe_s.
        """
        cfg = self.config
        if cfg.probe_s <= 0:
            return Q1, cause
        if self._probe_since_ns is None:
            if now_ns < self._probe_not_before_ns:
                return None
            self._probe_since_ns = now_ns
            self._note = f"probing the default flow with the camera ({cause})"
            return None
        camera_seen = len(self._cam) > 0
        if camera_seen and signals.t_cam_ms is not None and signals.t_cam_ms > cfg.rho[0]:
            self._end_probe(now_ns, f"camera latency {signals.t_cam_ms:.0f} ms > rho1")
            return None
        if now_ns - self._probe_since_ns >= self._ns(cfg.probe_s):
            self._probe_wait_ns = self._recover_ns
            return Q1, f"{cause}; the default flow carried the camera for {cfg.probe_s:g} s"
        return None

    def _end_probe(self, now_ns: int, why: str) -> None:
        cfg = self.config
        self._probe_since_ns = None
        longer = round(self._probe_wait_ns * cfg.recover_backoff)
        self._probe_wait_ns = min(longer, self._ns(cfg.recover_max_s))
        self._probe_not_before_ns = now_ns + self._probe_wait_ns
        self._note = f"probe failed: {why}; next try in {self._probe_wait_ns / NS_PER_S:g} s"

    def _enter(self, target: State, cause: str, signals: Signals, now_ns: int) -> Transition:
        cfg = self.config
        source = self.state
        transition = Transition(now_ns, source, target, cause, signals.p_lat, signals.p_cs)
        self.log.append(transition)
        if target is Q1 and cause != WATCHDOG_CAUSE:
            self._last_recovery_ns = now_ns
        bounced = (
            source is Q1
            and target in (Q3, Q4)
            and self._last_recovery_ns is not None
            and now_ns - self._last_recovery_ns < 2 * self._recover_ns
        )
        if bounced:  # HL came back soon after a recovery: wait longer before the next one (anti-flap)
            self._recover_ns = min(round(self._recover_ns * cfg.recover_backoff), self._ns(cfg.recover_max_s))
        self.state = target
        self._entered_ns = now_ns
        self._probe_since_ns = None
        self._ll_since_ns = now_ns if signals.latency is Latency.LL else None
        self._hl_since_ns = now_ns if signals.latency is Latency.HL else None
        if target is QA:
            # What the link did before the fallback says nothing about it now: recover on fresh evidence.
            self._cam.clear()
            self._cc.clear()
            self._ll_since_ns = self._hl_since_ns = None
        if target in RATE_ADAPTATION_STATES and source not in RATE_ADAPTATION_STATES:
            self._rate = cfg.rate_factor
            self._rate_changed_ns = now_ns
            self._min_rate_since_ns = now_ns if self._rate <= cfg.min_rate_factor else None
        return transition

    def step(self, inputs: Inputs, now_ns: int) -> Decision:
        signals = self._signals(inputs, now_ns)
        self._update_timers(signals, now_ns)
        if self.state is Q1 and now_ns - self._entered_ns >= self._ns(self.config.recover_max_s):
            self._recover_ns = self._ns(self.config.recover_s)  # calm for long: forget the backoff
        self._adapt_rate(signals, now_ns)
        self._note = ""
        probing = self._probe_since_ns is not None
        choice = self._choose(signals, now_ns)
        transition = self._enter(*choice, signals, now_ns) if choice else None
        if probing and self._probe_since_ns is not None and not self._recovering(signals):
            self._end_probe(now_ns, f"latency {signals.latency.value}")
        return Decision(self.state, self.actions(), signals, transition, self._note)

    def observe(self, inputs: Inputs, now_ns: int) -> Decision:
        """What the supervisor reads from the inputs, without acting on it: the drone on the ground.

        Nothing is flown from the edge there, the edge's first answers carry its start-up and the depth
        camera sees the ground, so what those signals would call for says nothing about the flight."""
        return Decision(self.state, self.actions(), self._signals(inputs, now_ns), None, "")

    def _recovering(self, signals: Signals) -> bool:
        """Whether the recovery condition that started the probe still holds."""
        high = _read_risk(signals) is Risk.HR
        return signals.latency is Latency.LL and (not high or self.state not in (Q2, Q3))


def _read_risk(signals: Signals) -> Risk:
    """The risk the machine acts on: NA before any depth reads as MR, NA after depth stopped as HR."""
    if signals.depth_lost:
        return Risk.HR
    return Risk.MR if signals.risk is Risk.NA else signals.risk
