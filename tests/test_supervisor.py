"""The PFSM as pure logic: property tests over random inputs and the paper's story on a fake clock."""

from __future__ import annotations

import itertools
import math
import random
from collections.abc import Callable
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dynqos.common.clock import FakeClock
from dynqos.common.config import SupervisorConfig
from dynqos.common.messages import SupervisorStatus, decode, encode
from dynqos.onboard.supervisor import (
    Q1,
    Q2,
    Q3,
    Q4,
    Q5,
    Q6,
    QA,
    TABLE_I,
    WATCHDOG_CAUSE,
    Actions,
    Decision,
    Inputs,
    Latency,
    Risk,
    State,
    Supervisor,
    sigmoid,
)
from dynqos.onboard.supervisor_status import to_status

TICK_S = 0.05  # 20 Hz
CONFIG = SupervisorConfig()

Profile = Callable[[float], Inputs]


class Flight:
    """Drives a supervisor at 20 Hz on a fake clock with inputs given as a function of time."""

    def __init__(self, config: SupervisorConfig = CONFIG) -> None:
        self.clock = FakeClock()
        self.sup = Supervisor(config, start_ns=self.clock.now_ns())
        self.decisions: list[tuple[float, Decision]] = []

    @property
    def t(self) -> float:
        return self.clock.now_ns() / 1e9

    def run(self, seconds: float, profile: Profile) -> Decision:
        decision = None
        for _ in range(round(seconds / TICK_S)):
            self.clock.advance_s(TICK_S)
            decision = self.sup.step(profile(self.t), self.clock.now_ns())
            self.decisions.append((self.t, decision))
        assert decision is not None
        return decision

    def run_until(self, state: State, limit_s: float, profile: Profile) -> float:
        """Seconds until the machine enters `state` (fails after limit_s)."""
        start = self.t
        while self.t - start < limit_s:
            if self.run(TICK_S, profile).state is state:
                return self.t - start
        pytest.fail(f"not in {state.value} after {limit_s} s; now {self.sup.state.value}: {self.path()}")

    def path(self) -> list[str]:
        return [
            f"{t.source.value}->{t.target.value}@{t.stamp_ns / 1e9:.2f}s ({t.cause})" for t in self.sup.log
        ]


def link(rtt_ms: float, cam_ms: float, space_m: float | None = 4.0, watchdog: bool = False) -> Profile:
    return lambda _t: Inputs(
        cc_rtts_ms=[rtt_ms], camera_latencies_ms=[cam_ms], spaciousness_m=space_m, watchdog_expired=watchdog
    )


UNLOADED = link(20.0, 40.0)
LOADED = link(90.0, 160.0)


def test_sigmoid_is_the_papers_and_safe_for_any_input() -> None:
    assert sigmoid(27.0, 5.0, 27.0) == 0.5
    assert sigmoid(28.0, 5.0, 27.0) == pytest.approx(1 / (1 + math.exp(-5)))
    assert sigmoid(1e308, 5.0, 27.0) == 1.0
    assert sigmoid(-1e308, 5.0, 27.0) == 0.0
    assert sigmoid(math.inf, 5.0, 27.0) == 1.0
    assert sigmoid(-math.inf, 5.0, 27.0) == 0.0
    with pytest.raises(ValueError, match="NaN"):
        sigmoid(math.nan, 5.0, 27.0)


def test_latency_condition_is_the_weighted_sum_over_window_means() -> None:
    sup = Supervisor(replace(CONFIG, cc_fast_window=0))  # the paper's t2 alone
    cams = [50.0 + i for i in range(15)]  # only the last 10 count
    rtts = [20.0 + (i % 5) for i in range(60)]  # only the last 50 count
    decision = sup.step(Inputs(camera_latencies_ms=cams, cc_rtts_ms=rtts), 0)
    t1 = sum(cams[-10:]) / 10
    t2 = sum(rtts[-50:]) / 50
    s = decision.signals
    assert s.t_cam_ms == pytest.approx(t1)
    assert s.t_cc_ms == pytest.approx(t2)
    expected = 0.35 * sigmoid(t1, 3, 61) + 0.65 * sigmoid(t2, 5, 27)
    assert s.p_lat == pytest.approx(expected)
    assert s.latency is (Latency.HL if expected > CONFIG.th_lat else Latency.LL)


def test_missing_samples_are_not_zero_latency() -> None:
    sup = Supervisor(CONFIG)
    decision = sup.step(Inputs(), 0)
    assert decision.signals.latency is Latency.NA
    assert decision.signals.p_lat is None
    assert decision.signals.risk is Risk.NA
    # Only camera samples: P_lat is P_cam alone, not diluted by a zero C&C term.
    decision = sup.step(Inputs(camera_latencies_ms=[200.0]), 1)
    assert decision.signals.p_cc is None
    assert decision.signals.p_lat == pytest.approx(decision.signals.p_cam)
    assert decision.signals.latency is Latency.HL
    # Garbage samples are ignored rather than poisoning the window.
    decision = sup.step(Inputs(cc_rtts_ms=[math.nan, -5.0, math.inf], spaciousness_m=math.nan), 2)
    assert decision.signals.t_cc_ms is None
    assert decision.signals.spaciousness_m is None


def test_a_fading_link_raises_latency_before_any_sample_only_when_radio_aware() -> None:
    """The modem's SINR (docs/radio.md): off by default; on, a SINR below radio_sinr_db is evidence of HL
    at once, and a good one never lowers what the samples say."""
    fading = Inputs(cc_rtts_ms=[20.0], camera_latencies_ms=[40.0], spaciousness_m=9.0, sinr_db=0.0)
    assert Supervisor(CONFIG).step(fading, 0).signals.latency is Latency.LL  # ignored by default
    aware = replace(CONFIG, radio_aware=True)
    signals = Supervisor(aware).step(fading, 0).signals
    assert signals.latency is Latency.HL
    assert signals.p_lat == pytest.approx(1.0 - sigmoid(0.0, aware.radio_mu, aware.radio_sinr_db))
    assert Supervisor(aware).step(Inputs(sinr_db=-23.0), 0).signals.latency is Latency.HL  # no samples yet
    clear = Supervisor(aware).step(replace(fading, sinr_db=20.0), 0).signals
    assert clear.latency is Latency.LL
    loaded = Supervisor(aware).step(Inputs(cc_rtts_ms=[90.0], camera_latencies_ms=[160.0], sinr_db=20.0), 0)
    assert loaded.signals.latency is Latency.HL  # a good SINR does not hide a queue
    assert Supervisor(aware).step(replace(fading, sinr_db=math.nan), 0).signals.latency is Latency.LL
    # In a flight: an LR drone whose link fades throttles its camera (q4) on the SINR alone, RTT still low.
    flight = Flight(aware)
    flight.run(2.0, link(20.0, 40.0, space_m=9.0))
    assert flight.run_until(Q4, 1.0, lambda _t: replace(fading, sinr_db=-5.0)) < 0.5


def test_the_cores_delay_report_raises_latency_only_when_network_aware() -> None:
    """The 5G core's QoS monitoring (docs/supervisor.md): off by default; on, a fresh round trip read as
    a C&C RTT is evidence of HL at once, and a low one never lowers what the samples say."""
    reported = Inputs(cc_rtts_ms=[20.0], camera_latencies_ms=[40.0], spaciousness_m=4.0, network_rtt_ms=90.0)
    assert Supervisor(CONFIG).step(reported, 0).signals.latency is Latency.LL  # ignored by default
    aware = replace(CONFIG, network_aware=True)
    signals = Supervisor(aware).step(reported, 0).signals
    assert signals.latency is Latency.HL
    assert signals.p_lat == pytest.approx(sigmoid(90.0, aware.mu[1], aware.rho[1]))
    assert Supervisor(aware).step(Inputs(network_rtt_ms=90.0), 0).signals.latency is Latency.HL  # alone
    assert Supervisor(aware).step(replace(reported, network_rtt_ms=10.0), 0).signals.latency is Latency.LL
    loaded = Inputs(cc_rtts_ms=[90.0], camera_latencies_ms=[160.0], network_rtt_ms=10.0)
    assert Supervisor(aware).step(loaded, 0).signals.latency is Latency.HL  # a low report hides no queue
    assert Supervisor(aware).step(replace(reported, network_rtt_ms=math.inf), 0).signals.latency is Latency.LL
    # In a flight: an MR drone moves to the priority flow (q3) on the report alone, its own RTT still low.
    flight = Flight(aware)
    flight.run(2.0, link(20.0, 40.0, space_m=4.0))
    assert flight.run_until(Q3, 1.0, lambda _t: reported) < 0.5


def test_unanswered_requests_raise_latency_when_acks_stop() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    assert flight.sup.state is Q1
    # Acks stop: no new samples, but the oldest unanswered state grows older.
    elapsed = flight.run_until(
        Q3, 3.0, lambda t: Inputs(cc_outstanding_ms=(t - 2.0) * 1000, camera_outstanding_ms=math.inf)
    )
    assert elapsed < 1.0


def test_risk_filter_and_levels() -> None:
    sup = Supervisor(CONFIG)
    d = sup.step(Inputs(spaciousness_m=10.0), 0)
    assert (d.signals.spaciousness_m, d.signals.risk) == (10.0, Risk.LR)
    d = sup.step(Inputs(spaciousness_m=0.0), 1)
    assert d.signals.spaciousness_m == pytest.approx(8.0)  # 0.8 * 10 + 0.2 * 0
    for _ in range(3):
        d = sup.step(Inputs(spaciousness_m=0.0), 2)
    assert d.signals.spaciousness_m == pytest.approx(8.0 * 0.8**3)
    assert d.signals.risk is Risk.MR
    d = sup.step(Inputs(spaciousness_m=0.0), 3)
    assert d.signals.risk is Risk.MR  # 3.28 m
    d = sup.step(Inputs(spaciousness_m=0.0), 4)
    assert d.signals.risk is Risk.HR  # 2.62 m
    assert d.signals.p_cs is not None
    assert d.signals.p_cs > 0.5


def test_paper_story_mr_load_priority_rate_adaptation_fallback_and_back() -> None:
    flight = Flight()
    assert flight.run(3.0, UNLOADED).state is Q1
    # Background load starts while risk is MR: q1 -> q3 within the latency window.
    assert flight.run_until(Q3, 1.5, LOADED) < 1.0
    decision = flight.sup.step(LOADED(flight.t), flight.clock.now_ns())
    assert (decision.actions.flow, decision.actions.camera_rate_factor) == ("priority", 1.0)
    # HL persists even on the priority flow: rate adaptation.
    flight.run_until(Q6, CONFIG.escalate_s + 1.0, LOADED)
    assert flight.sup.actions().camera_rate_factor == CONFIG.rate_factor
    assert flight.sup.actions().flow == "priority"
    # HL persists at the minimum rate: full onboard autonomy.
    flight.run_until(QA, CONFIG.escalate_s + 3.0, LOADED)
    assert flight.sup.actions().control_source == "fallback"
    # Load ends: back to q1 once the windows show LL long enough.
    back = flight.run_until(Q1, 10.0, UNLOADED)
    assert back > CONFIG.recover_s
    actions = flight.sup.actions()
    assert (actions.flow, actions.camera_rate_factor, actions.control_source) == ("default", 1.0, "edge")
    assert [(t.source, t.target) for t in flight.sup.log] == [(Q1, Q3), (Q3, Q6), (Q6, QA), (QA, Q1)]


def test_hr_proactively_selects_priority_with_low_latency() -> None:
    flight = Flight()
    flight.run_until(Q2, 2.0, link(20.0, 40.0, space_m=2.0))
    assert flight.sup.log[-1].cause.startswith("HR")
    assert flight.decisions[-1][1].signals.latency is Latency.LL
    assert flight.sup.actions().flow == "priority"
    # HL persists in HR: rate adaptation in the HR context.
    flight.run_until(Q5, CONFIG.escalate_s + 1.0, link(90.0, 160.0, space_m=2.0))
    # Space opens and latency is low again: back to q1.
    flight.run_until(Q1, 8.0, link(20.0, 40.0, space_m=8.0))


def test_q2_returns_to_q1_when_space_opens() -> None:
    flight = Flight()
    flight.run_until(Q2, 2.0, link(20.0, 40.0, space_m=2.0))
    flight.run_until(Q1, 10.0, link(20.0, 40.0, space_m=9.0))
    assert flight.sup.log[-1].cause.startswith("LL holds and risk is no longer HR;")


def test_lr_and_hl_throttles_the_camera_on_the_default_flow_then_falls_back() -> None:
    flight = Flight()
    flight.run(2.0, link(20.0, 40.0, space_m=9.0))
    flight.run_until(Q4, 2.0, link(90.0, 160.0, space_m=9.0))
    assert flight.sup.actions().flow == "default"
    assert flight.sup.actions().camera_rate_factor == CONFIG.rate_factor
    rates = []
    while flight.sup.state is Q4 and flight.t < 20:
        rates.append(flight.run(TICK_S, link(90.0, 160.0, space_m=9.0)).actions.camera_rate_factor)
    assert flight.sup.state is QA
    assert min(rates) == CONFIG.min_rate_factor
    assert rates == sorted(rates, reverse=True)


def test_q4_moves_to_priority_when_risk_rises_and_recovers() -> None:
    flight = Flight()
    flight.run(2.0, link(20.0, 40.0, space_m=9.0))
    flight.run_until(Q4, 2.0, link(90.0, 160.0, space_m=9.0))
    flight.run_until(Q6, 3.0, link(90.0, 160.0, space_m=4.0))
    flight.run_until(Q1, 10.0, link(20.0, 40.0, space_m=4.0))
    flight.run_until(Q4, 3.0, link(90.0, 160.0, space_m=9.0))
    flight.run_until(Q1, 15.0, link(20.0, 40.0, space_m=9.0))


def test_q3_escalates_to_q5_in_hr_context() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    flight.run_until(Q5, CONFIG.escalate_s + 1.0, link(90.0, 160.0, space_m=0.5))


def denied(profile: Profile) -> Profile:
    """The same link, with the network refusing the priority flow (the QoS agent's UNAVAILABLE)."""
    return lambda t: replace(profile(t), priority_denied=True)


@pytest.mark.parametrize(("space_m", "start", "target"), [(4.0, Q3, Q6), (2.0, Q2, Q5)])
def test_refused_priority_goes_to_rate_adaptation_without_waiting_for_it_to_help(
    space_m: float, start: State, target: State
) -> None:
    flight = Flight()
    flight.run(2.0, link(20.0, 40.0, space_m=space_m))
    flight.run_until(start, 2.0, link(90.0, 160.0, space_m=space_m))
    flight.run(CONFIG.dwell_s, link(90.0, 160.0, space_m=space_m))  # granted or not, q3/q2 is held its dwell
    took = flight.run_until(target, CONFIG.escalate_s, denied(link(90.0, 160.0, space_m=space_m)))
    assert took < 0.5 < CONFIG.escalate_s  # persist_s, not escalate_s
    assert "the network refused" in flight.sup.log[-1].cause


def test_q3_recovers_when_priority_flow_fixes_latency() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    assert flight.run_until(Q1, 8.0, UNLOADED) >= CONFIG.recover_s


def test_repeated_bounces_lengthen_the_recovery_time() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    stays = []
    for _ in range(3):
        flight.run_until(Q3, 3.0, LOADED)
        stays.append(flight.run_until(Q1, 40.0, UNLOADED))
    assert stays[1] > stays[0] + 1.0
    assert stays[2] > stays[1] + 1.0
    # Calm for recover_max_s: the backoff is forgotten.
    flight.run(CONFIG.recover_max_s + 1, UNLOADED)
    flight.run_until(Q3, 3.0, LOADED)
    assert flight.run_until(Q1, 40.0, UNLOADED) < stays[1]


def test_the_flows_back_off_never_keeps_a_drone_in_its_fallback() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    for _ in range(3):  # three quick returns to q1: the next one waits 8 s
        flight.run_until(Q3, 3.0, LOADED)
        flight.run_until(Q1, 40.0, UNLOADED)
    flight.run(0.2, lambda _t: Inputs(watchdog_expired=True))
    assert flight.sup.state is QA
    # The link is back: control returns to the edge after the plain recovery time, not the backed-off one.
    assert flight.run_until(Q1, 40.0, UNLOADED) <= CONFIG.recover_s + CONFIG.dwell_s + 0.1


def test_watchdog_sends_any_state_to_qa_in_the_same_tick_and_qa_waits_for_the_link() -> None:
    for reach, profile in ((Q1, UNLOADED), (Q3, LOADED), (Q2, link(20.0, 40.0, space_m=1.0))):
        flight = Flight()
        flight.run_until(reach, 5.0, profile)
        decision = flight.sup.step(Inputs(watchdog_expired=True), flight.clock.now_ns() + 1)
        assert decision.state is QA
        assert decision.transition is not None
        assert decision.transition.cause == WATCHDOG_CAUSE
        assert decision.actions.control_source == "fallback"
    flight = Flight()
    flight.run(1.0, link(20.0, 40.0, watchdog=True))
    assert flight.sup.state is QA
    flight.run(5.0, link(20.0, 40.0, watchdog=True))
    assert flight.sup.state is QA  # low latency alone does not end qA while commands are missing
    flight.run_until(Q1, 5.0, UNLOADED)


def test_qa_needs_fresh_evidence_to_recover() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)  # low latency before the link is lost...
    flight.run(1.0, lambda _t: Inputs(watchdog_expired=True))
    assert flight.sup.state is QA
    flight.run(5.0, lambda _t: Inputs())  # ...says nothing about the link now
    assert flight.sup.state is QA
    assert flight.decisions[-1][1].signals.latency is Latency.NA


def test_observing_reads_the_signals_and_never_moves() -> None:
    """The drone on the ground: HL, HR and a missed command are all read, and none moves the machine."""
    flight = Flight()
    ground = link(90.0, 160.0, space_m=0.3, watchdog=True)
    for _ in range(round(10.0 / TICK_S)):
        flight.clock.advance_s(TICK_S)
        decision = flight.sup.observe(ground(flight.t), flight.clock.now_ns())
        assert (decision.state, decision.transition) == (Q1, None)
    assert decision.signals.latency is Latency.HL
    assert decision.signals.risk is Risk.HR
    assert decision.signals.watchdog
    assert decision.actions.flow == "default"
    assert not flight.sup.log
    # the same signals, judged, move it at once
    assert flight.sup.step(ground(flight.t), flight.clock.now_ns() + 1).state is QA


def test_status_message_carries_the_decision() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    decision = flight.decisions[-1][1]
    status = to_status(decision, uav="uav1", seq=7, stamp_ns=flight.clock.now_ns(), last=flight.sup.log[-1])
    assert decode(encode(status)) == status
    assert (status.state, status.prev_state, status.flow, status.latency) == ("q3", "q1", "priority", "HL")
    assert status.p_lat == pytest.approx(decision.signals.p_lat)
    empty = to_status(Supervisor(CONFIG).step(Inputs(), 0), uav="uav1", seq=0, stamp_ns=0, last=None)
    assert isinstance(empty, SupervisorStatus)
    assert (empty.latency, empty.risk, empty.cause, empty.p_lat) == ("NA", "NA", "", 0.0)


def test_transition_log_is_bounded() -> None:
    flight = Flight(
        replace(CONFIG, dwell_s=0.0, recover_s=0.0, recover_max_s=0.0, persist_s=0.0, escalate_s=0.0)
    )
    for i in range(1200):
        flight.run(TICK_S, link(20.0, 40.0, watchdog=i % 2 == 0))
    assert len(flight.sup.log) == 1000


# ---- properties over random input sequences -------------------------------------------------------


@st.composite
def sequences(draw: st.DrawFn) -> list[tuple[int, Inputs]]:
    """Piecewise regimes (quiet, near-threshold noise, loaded, link lost) with noise inside each,
    so that persistence and dwell timers are exercised, not just independent random ticks."""
    rng = random.Random(draw(st.integers(0, 2**32)))
    steps: list[tuple[int, Inputs]] = []
    for _ in range(draw(st.integers(1, 8))):
        rtt = draw(st.sampled_from([15.0, 26.0, 28.0, 90.0, 300.0]))
        cam = draw(st.sampled_from([40.0, 60.0, 160.0]))
        space = draw(st.sampled_from([None, 1.0, 2.9, 3.1, 4.9, 5.1, 9.0]))
        watchdog_rate = draw(st.sampled_from([0.0, 0.0, 0.05, 1.0]))
        acks_lost = draw(st.booleans())
        for _ in range(rng.randint(1, 60)):
            steps.append(
                (
                    rng.randint(10, 120) * 1_000_000,
                    Inputs(
                        cc_rtts_ms=[] if acks_lost else [max(0.0, rng.gauss(rtt, rtt / 5))],
                        camera_latencies_ms=[] if rng.random() < 0.5 else [max(0.0, rng.gauss(cam, cam / 5))],
                        cc_outstanding_ms=rng.uniform(0, 500) if acks_lost else None,
                        spaciousness_m=None if space is None else max(0.0, rng.gauss(space, 0.3)),
                        watchdog_expired=rng.random() < watchdog_rate,
                    ),
                )
            )
    return steps


configs = st.builds(
    SupervisorConfig,
    mode=st.sampled_from(["deterministic", "stochastic"]),
    seed=st.integers(0, 2**32),
    dwell_s=st.sampled_from([0.0, 0.2, 1.0]),
    persist_s=st.sampled_from([0.0, 0.3]),
    escalate_s=st.sampled_from([0.0, 0.3, 3.0]),
    recover_s=st.sampled_from([0.0, 0.5, 2.0]),
    rate_step_s=st.sampled_from([0.0, 0.5]),
)


def replay(config: SupervisorConfig, steps: list[tuple[int, Inputs]]) -> list[Decision]:
    sup = Supervisor(config)
    now = 0
    out = []
    for delta, inputs in steps:
        now += delta
        out.append(sup.step(inputs, now))
    return out


@given(configs, sequences())
def test_only_table_i_transitions_ever_and_watchdog_within_one_tick(
    config: SupervisorConfig, steps: list[tuple[int, Inputs]]
) -> None:
    previous = Q1
    for (_, inputs), decision in zip(steps, replay(config, steps), strict=True):
        if decision.transition is not None:
            t = decision.transition
            assert t.source is previous
            assert t.target in TABLE_I[t.source] or (t.cause == WATCHDOG_CAUSE and t.target is QA), t
        else:
            assert decision.state is previous
        if inputs.watchdog_expired:
            assert decision.state is QA
            assert decision.actions.control_source == "fallback"
        previous = decision.state


@given(configs, sequences())
def test_no_state_changes_faster_than_its_dwell_time(
    config: SupervisorConfig, steps: list[tuple[int, Inputs]]
) -> None:
    dwell_ns = round(config.dwell_s * 1e9)
    entered = 0
    for decision in replay(config, steps):
        t = decision.transition
        if t is None:
            continue
        if t.cause != WATCHDOG_CAUSE:
            assert t.stamp_ns - entered >= dwell_ns
        entered = t.stamp_ns


@given(configs.map(lambda c: replace(c, mode="stochastic")), sequences())
def test_stochastic_mode_is_reproducible_for_a_seed(
    config: SupervisorConfig, steps: list[tuple[int, Inputs]]
) -> None:
    first = [(d.state, d.actions) for d in replay(config, steps)]
    second = [(d.state, d.actions) for d in replay(config, steps)]
    assert first == second


def test_stochastic_mode_fires_with_the_signals_probability() -> None:
    config = replace(CONFIG, mode="stochastic", seed=1)
    entries = []
    for seed in range(40):
        flight = Flight(replace(config, seed=seed))
        flight.run(2.0, UNLOADED)
        entries.append(flight.run_until(Q3, 5.0, link(28.0, 40.0)))
    # P_lat is ~0.6 here, so the machine enters q3 after a few ticks, not always on the first.
    assert min(entries) < max(entries)
    assert len({round(e, 2) for e in entries}) > 3


def ramp(onset_s: float, slope_ms_per_s: float, cam_ms: float = 40.0) -> Profile:
    """A queue building from onset_s: the RTT grows by slope per second (as under an overload)."""
    return lambda t: Inputs(
        cc_rtts_ms=[15.0 + max(0.0, t - onset_s) * slope_ms_per_s],
        camera_latencies_ms=[cam_ms],
        spaciousness_m=4.0,
    )


def test_fast_attack_sees_a_queue_building_within_a_few_samples() -> None:
    reactions = []
    for fast_window in (4, 0):
        flight = Flight(replace(CONFIG, cc_fast_window=fast_window))
        flight.run(3.0, ramp(99.0, 0.0))  # a quiet 15 ms link
        onset = flight.t
        reactions.append(flight.run_until(Q3, 2.0, ramp(onset, 300.0)))
    fast, paper = reactions
    assert fast <= 0.3  # 4 samples above rho2 on average, then persist_s
    assert paper >= fast + 0.25  # the 50-sample mean alone lets the queue grow twice as long


def test_fast_attack_counts_the_state_still_unanswered() -> None:
    sup = Supervisor(CONFIG)
    quiet = sup.step(Inputs(cc_rtts_ms=[15.0] * 50, camera_latencies_ms=[40.0]), 0)
    assert quiet.signals.t_cc_ms == pytest.approx(15.0)
    waiting = sup.step(Inputs(cc_outstanding_ms=95.0), 1)
    assert waiting.signals.t_cc_ms == pytest.approx((15.0 * 3 + 95.0) / 4)
    few = Supervisor(CONFIG).step(Inputs(cc_rtts_ms=[15.0, 16.0], cc_outstanding_ms=10.0), 0)
    assert few.signals.t_cc_ms == pytest.approx(15.5)  # fewer than 4 samples: the plain mean


class LoadedDefaultFlow:
    """The cell stays loaded: the priority flow is fine, the default flow queues whatever is put on it."""

    def __init__(self, flight: Flight, loaded: bool = True) -> None:
        self.flight = flight
        self.loaded = loaded

    def __call__(self, _t: float) -> Inputs:
        camera_on_default = self.flight.sup.actions().camera_flow == "default"
        cam = 150.0 if camera_on_default and self.loaded else 40.0
        return Inputs(cc_rtts_ms=[15.0], camera_latencies_ms=[cam], spaciousness_m=4.0)


def notes(flight: Flight) -> list[tuple[float, str]]:
    return [(t, d.note) for t, d in flight.decisions if d.note]


def test_recovery_sends_the_camera_ahead_and_stays_when_the_default_flow_is_still_loaded() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    cell = LoadedDefaultFlow(flight)
    flight.run(20.0, cell)
    assert flight.sup.state is Q3  # never went back to q1 while the default flow was loaded
    started = [t for t, n in notes(flight) if n.startswith("probing")]
    failed = [t for t, n in notes(flight) if n.startswith("probe failed: camera latency")]
    assert len(started) == len(failed) >= 2
    gaps = [b - a for a, b in itertools.pairwise(started)]
    assert gaps == sorted(gaps)  # each try waits longer than the one before
    assert gaps[-1] > gaps[0] + 1.0
    probing = [d.actions for _, d in flight.decisions if d.actions.camera_flow != d.actions.flow]
    assert probing
    assert {(a.flow, a.camera_flow, a.camera_rate_factor) for a in probing} == {("priority", "default", 1.0)}
    # The load ends: the next probe passes and the machine returns to q1 after probe_s.
    cell.loaded = False
    flight.run_until(Q1, CONFIG.recover_max_s + 3.0, cell)
    assert flight.sup.log[-1].cause == "LL holds; the default flow carried the camera for 1 s"
    assert flight.sup.actions() == Actions("default", 1.0, "edge", "default")
    status = to_status(flight.decisions[-1][1], uav="uav1", seq=1, stamp_ns=0, last=None)
    assert status.camera_flow == "default"


def test_a_probe_ends_when_the_latency_turns_high() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    while not flight.decisions[-1][1].note.startswith("probing"):
        flight.run(TICK_S, UNLOADED)
    assert flight.sup.actions().camera_flow == "default"
    status = to_status(flight.decisions[-1][1], uav="uav1", seq=1, stamp_ns=0, last=None)
    assert (status.flow, status.camera_flow) == ("priority", "default")
    flight.run(TICK_S, LOADED)
    assert flight.decisions[-1][1].note.startswith("probe failed: latency HL")
    assert flight.sup.actions().camera_flow == "priority"
    assert flight.sup.state is Q3


def test_rate_adapted_states_probe_at_full_rate_and_q4_returns_at_once() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    flight.run_until(Q6, CONFIG.escalate_s + 1.0, LOADED)
    assert flight.sup.actions().camera_rate_factor == CONFIG.rate_factor
    while not flight.decisions[-1][1].note.startswith("probing"):
        flight.run(TICK_S, UNLOADED)
    assert flight.sup.actions() == Actions("priority", 1.0, "edge", "default")
    flight.run_until(Q1, 2.0, UNLOADED)
    # q4 is already on the default flow: nothing to probe.
    flight = Flight()
    flight.run(2.0, link(20.0, 40.0, space_m=9.0))
    flight.run_until(Q4, 2.0, link(90.0, 160.0, space_m=9.0))
    flight.run_until(Q1, 10.0, link(20.0, 40.0, space_m=9.0))
    assert not [n for _, n in notes(flight) if n.startswith("probing")]


def test_probe_s_zero_returns_at_once_as_in_the_paper() -> None:
    flight = Flight(replace(CONFIG, probe_s=0.0))
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    flight.run_until(Q1, CONFIG.recover_s + 1.5, UNLOADED)
    assert flight.sup.log[-1].cause == "LL holds"
    assert not notes(flight)


def no_camera_acks(rtt_ms: float) -> Profile:
    """Frames go out and nothing acknowledges them (no detector): only an ever older outstanding frame."""
    return lambda t: Inputs(cc_rtts_ms=[rtt_ms], camera_outstanding_ms=1000.0 * t, spaciousness_m=4.0)


def test_without_camera_acks_the_probe_has_no_evidence_and_returns_after_probe_s() -> None:
    flight = Flight()
    flight.run(2.0, no_camera_acks(20.0))
    flight.run_until(Q3, 2.0, no_camera_acks(90.0))
    took = flight.run_until(Q1, 10.0, no_camera_acks(20.0))
    assert CONFIG.recover_s + CONFIG.probe_s <= took <= CONFIG.recover_s + CONFIG.probe_s + 1.0
    assert not [n for _, n in notes(flight) if n.startswith("probe failed")]


def test_failed_probes_do_not_slow_the_return_from_the_fallback() -> None:
    flight = Flight()
    flight.run(2.0, UNLOADED)
    flight.run_until(Q3, 2.0, LOADED)
    flight.run(12.0, LoadedDefaultFlow(flight))  # probes fail and back off
    assert len([n for _, n in notes(flight) if n.startswith("probe failed")]) >= 2
    flight.run(0.5, link(20.0, 40.0, watchdog=True))
    assert flight.sup.state is QA
    assert flight.run_until(Q1, 5.0, UNLOADED) <= CONFIG.recover_s + 0.5


def test_depth_that_stops_is_held_then_unknown_and_read_as_high_risk_until_it_returns() -> None:
    """A camera gone or a recording ended: the last depth holds for risk_stale_s; then the risk is NA
    (reported so, with depth_lost) and the machine reads it as HR: priority, no throttling. Depth back:
    the filter starts from the new sample (not the old space) and q2 recovers as usual."""
    flight = Flight()
    flight.run(2.0, link(20.0, 40.0, space_m=8.0))
    assert flight.sup.state is Q1
    blind = link(20.0, 40.0, space_m=None)
    held = flight.run(CONFIG.risk_stale_s - 0.1, blind)
    assert held.signals.risk is Risk.LR  # still the last depth
    assert not held.signals.depth_lost
    assert flight.run_until(Q2, 1.0, blind) <= 0.2 + CONFIG.dwell_s
    lost = flight.decisions[-1][1]
    assert lost.signals.depth_lost
    assert lost.signals.risk is Risk.NA
    assert lost.signals.spaciousness_m is None
    assert flight.sup.log[-1].cause == "HR: proactive priority"
    status = to_status(lost, uav="uav1", seq=1, stamp_ns=flight.clock.now_ns(), last=flight.sup.log[-1])
    assert status.risk == "NA"
    assert status.depth_lost
    assert decode(encode(status)) == status
    flight.run(5.0, blind)
    assert flight.sup.state is Q2  # blind: it stays on the priority flow, however calm the link
    back = flight.run(TICK_S, link(20.0, 40.0, space_m=8.0))
    assert not back.signals.depth_lost
    assert back.signals.spaciousness_m == 8.0  # a fresh filter: the first sample, not a blend
    flight.run_until(Q1, 10.0, link(20.0, 40.0, space_m=8.0))
    assert flight.sup.log[-1].cause.startswith("LL holds and risk is no longer HR")


def test_no_depth_ever_is_not_lost_depth() -> None:
    """A drone without a depth camera never had depth to lose: NA, read as MR, never depth_lost."""
    flight = Flight()
    decision = flight.run(CONFIG.risk_stale_s + 2.0, link(20.0, 40.0, space_m=None))
    assert decision.signals.risk is Risk.NA
    assert not decision.signals.depth_lost
    assert flight.sup.state is Q1
