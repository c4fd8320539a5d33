"""The figures that compare dynqos's vehicle with PX4 (bench/vehicle_compare.py), on made-up responses
whose answers are known."""

from __future__ import annotations

import math

import pytest

from dynqos.bench.vehicle_compare import circle_rmse, drift, lag_and_gain, step_response


def test_a_step_response_gives_its_delay_rise_overshoot_and_final_error() -> None:
    # nothing for 0.2 s, then a straight climb from 0 to 1.2 in 1 s, then settling at 1.0
    def value(t: float) -> float:
        if t < 0.2:
            return 0.0
        return min(1.2, 1.2 * (t - 0.2)) if t < 1.2 else 1.0

    samples = [(i / 100, 5.0 + value(i / 100)) for i in range(300)]
    step = step_response(samples, start=5.0, target=6.0)
    assert step.delay_s == pytest.approx(0.2 + 0.05 / 1.2, abs=0.011)
    assert step.rise_s == pytest.approx(0.8 / 1.2, abs=0.02)
    assert step.overshoot_pct == pytest.approx(20.0, abs=1.5)  # the peak falls between samples
    assert step.final_error_m == pytest.approx(0.0)
    down = step_response([(t, 5.0 - (v - 5.0)) for t, v in samples], start=5.0, target=4.0)
    assert down.rise_s == step.rise_s  # a step down is read the same way


def test_a_response_that_never_gets_there_has_no_rise_time() -> None:
    step = step_response([(t / 10, 0.5) for t in range(10)], start=0.0, target=1.0)
    assert (step.rise_s, step.overshoot_pct, step.final_error_m) == (None, 0.0, 0.5)


def test_lag_and_gain_of_a_delayed_and_halved_velocity() -> None:
    times = [i * 0.02 for i in range(150)]
    wanted = [math.sin(t * 3) for t in times]
    flown = [0.5 * math.sin((t - 0.1) * 3) if t >= 0.1 else 0.0 for t in times]
    lag, gain = lag_and_gain(times, wanted, flown)
    assert lag == pytest.approx(0.1, abs=0.021)
    assert gain == pytest.approx(0.5, abs=0.01)


def test_hover_drift_and_circle_error() -> None:
    samples = [(0.0, (1.0, 0.0, -1.5), (0, 0, 0)), (1.0, (0.0, 0.0, -1.5), (0, 0, 0))]
    assert drift(samples, (0.0, 0.0, -1.5)) == {"rms_m": math.sqrt(0.5), "max_m": 1.0}
    assert circle_rmse(samples, lambda _t: (0.0, 0.0, -1.5), since_s=0.5) == 0.0
