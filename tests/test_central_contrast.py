"""The paper's central claim, flown: without QoS the drone's latency climbs once the cell is loaded; with
dynamic QoS the supervisor moves to the priority flow because of that latency, within a second, and the
latency stays near the baseline. And the failure does not depend on the scale the experiment runs at.

Both flights hover at the same point (the no-QoS scenario's mission), so the QoS mode is the only
difference, and the dynamic one meets the load at medium risk: its move to the priority flow can only
be the latency's doing. It fails if the supervisor stops reacting to high latency (rho2 out of reach),
if the priority bearer loses its weight, or if the drone offers no more than its fair share of the
loaded cell (the camera sized on views it does not fly).
"""

from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.config import CellConfig
from dynqos.experiment.runner import run_scenario
from dynqos.plan.scenario import Scenario, builtin_scenario
from tests.flights import fly_for_behaviour, not_ours

FAIR_SHARE_MBPS = CellConfig().uplink_mbps / 2  # the drone and one background user, equal weights
DURATION_S = 18.0
BG_START_S = 8.0
SWITCH_BOUND_S = 1.0  # the move to the priority flow, after the load starts
BACK_BOUND_S = 1.5  # the RTT back within 1.2x of the baseline, after that move (the queue drained)


def _steady_before_the_load(summary: dict[str, Any]) -> bool:
    """Before the load the cell is idle, so nothing but the machine can slow the drone there: its camera
    kept 90% of its rate, and (dynamic QoS) it did not leave the default flow for latency. CI on a busy
    2-core host saw both break for minutes (12.5 of 15 frames/s; "before the load: MR and HL", a round
    trip of 16 ms here past rho2's 27 ms there) while the same commit's flights held them locally."""
    fps = summary["camera_fps"]
    moved = str(summary.get("first_qos_switch_cause") or "").startswith("before the load")
    return fps["baseline"] >= 0.9 * fps["configured"] and not moved


def _disturbed(summary: dict[str, Any]) -> bool:
    return not_ours(summary) or not _steady_before_the_load(summary)


def _fly_no_qos(scenario: Scenario, tmp_path: Path) -> dict[str, Any]:
    """bg-noqos flown (again once, if its machine did not keep the camera's rate; tests/flights.py)."""

    def check(result: dict[str, Any], _: Path) -> None:
        assert result["ok"], result["failure"]
        assert _steady_before_the_load(result), result["camera_fps"]  # the machine kept the rate up

    return fly_for_behaviour(
        lambda out: run_scenario(scenario, out, progress=False), tmp_path, check, _disturbed
    )


@pytest.fixture(scope="module")
def no_qos(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """bg-noqos at the default scale, flown once for both tests below."""
    scenario = replace(builtin_scenario("bg-noqos"), duration_s=DURATION_S, bg_start_s=BG_START_S)
    return _fly_no_qos(scenario, tmp_path_factory.mktemp("noqos"))


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(420)
@pytest.mark.parametrize("backend", ["camara", "nef", "links"])
def test_without_qos_latency_climbs_and_dynamic_qos_switches_on_it_and_holds(
    no_qos: dict[str, Any], tmp_path: Path, backend: str
) -> None:
    """With each way the network gives the priority flow its weight (docs/qos.md): a QoD session the
    QoS agent asks the emulated operator for, a subscription it asks the emulated 5G core's NEF for, or
    a static policy for the priority port."""
    without = no_qos
    assert without["uav_offered_mbps"] > FAIR_SHARE_MBPS  # the drone asks for more than its share...
    assert without["uav_delivered_mbps"] < without["uav_offered_mbps"]  # ...and does not get it
    assert without["uav_delivered_mbps"] <= 1.02 * FAIR_SHARE_MBPS
    baseline, loaded = without["rtt_ms"]["baseline"], without["rtt_ms"]["loaded"]
    print(f"no QoS: RTT {baseline['mean']:.1f} ms before the load, p95 {loaded['p95']:.1f} ms under it")
    assert loaded["p95"] >= 3 * baseline["mean"]

    dynamic = replace(
        builtin_scenario("bg-dynqos-hover"), duration_s=DURATION_S, bg_start_s=BG_START_S, qos_backend=backend
    )
    noqos = builtin_scenario("bg-noqos")
    assert (dynamic.mission, dynamic.bg_mbps) == (noqos.mission, noqos.bg_mbps)  # only the QoS differs
    with_qos = fly_for_behaviour(
        lambda out: run_scenario(dynamic, out, progress=False), tmp_path, _switches_on_the_load, _disturbed
    )
    assert with_qos["qos_network"]["backend"] == backend


def _switches_on_the_load(with_qos: dict[str, Any], out: Path) -> None:
    """The dynamic flight moved to the priority flow for the load's latency, within a second of it; its
    RTT came back soon after and held there; the network granted it by the scenario's backend.

    "Held" is judged after the switch and the drain (at most SWITCH_BOUND_S + BACK_BOUND_S into the load):
    the mean over the whole 10 s loaded window also weighs the second in which the load met the default
    flow (in a flight whose baseline was 15.7 ms: 47 ms on average in that second, 113 at most; the
    window's mean 1.27x the baseline, from 2.5 s into the load 1.08x). The bound on the time back is
    what judges that second."""
    cause = with_qos["first_qos_switch_cause"]
    switch_s = with_qos["first_qos_switch_after_bg_s"]
    back_s = with_qos["qos_network"]["decision_to_rtt_back_s"]
    baseline = with_qos["rtt_ms"]["baseline"]["mean"]
    held = _rtts_from(out / with_qos["scenario"] / "latency.csv", BG_START_S + SWITCH_BOUND_S + BACK_BOUND_S)
    held_mean = sum(held) / len(held)
    print(
        f"dynamic QoS: switch {switch_s} s ({cause}), back {back_s} s later; "
        f"RTT {baseline:.1f} ms, then held {held_mean:.1f} ms"
    )
    assert cause is not None
    assert "HL" in cause
    assert not cause.startswith("before the load")
    assert switch_s <= SWITCH_BOUND_S
    assert back_s is not None
    assert back_s <= BACK_BOUND_S
    assert len(held) >= 100  # 7.5 s of 20 Hz states
    assert held_mean <= 1.3 * baseline
    network = with_qos["qos_network"]
    backend = network["backend"]
    assert network["grant_at_end"] == "available"
    assert network["decision_to_available_s"] is not None
    if backend == "camara":
        assert network["sessions"]["created"] >= 1
        assert network["sessions"]["open_at_end"] == 0
    elif backend == "nef":
        assert network["subscriptions"]["created"] >= 1
        assert network["subscriptions"]["deleted"] == network["subscriptions"]["created"]
        assert network["subscriptions"]["open_at_end"] == 0
        assert "sessions" not in network  # the QoD API was not asked
    else:
        assert "sessions" not in network  # the network was never asked
        assert "subscriptions" not in network


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(420)
def test_the_no_qos_failure_is_the_same_at_scale_3_and_scale_10(
    no_qos: dict[str, Any], tmp_path: Path
) -> None:
    """Every rate and every buffer in front of the cell is scaled, so a queue holds the same time at any
    scale: bg-noqos's loaded RTT agrees at scale 3 and 10 (measured in 20 s flights: 225.8 and 235.7 ms).
    It fails if a buffer stops scaling (unscaled socket buffers put 0.45 s more into the scale-10 queue)
    or the camera stops offering its rate at one of them."""
    scenario = replace(builtin_scenario("bg-noqos"), duration_s=DURATION_S, bg_start_s=BG_START_S, scale=3.0)
    at_3 = _fly_no_qos(scenario, tmp_path)
    loaded_3, loaded_10 = at_3["rtt_ms"]["loaded"]["mean"], no_qos["rtt_ms"]["loaded"]["mean"]
    print(f"bg-noqos loaded RTT mean: {loaded_3:.1f} ms at scale 3, {loaded_10:.1f} ms at scale 10")
    assert loaded_3 >= 3 * at_3["rtt_ms"]["baseline"]["mean"]
    assert loaded_10 == pytest.approx(loaded_3, rel=0.25)


def _rtts_from(latency_csv: Path, since_s: float) -> list[float]:
    """The flight's round trips (latency.csv) from `since_s` into it."""
    with latency_csv.open() as f:
        return [
            float(r["ms"]) for r in csv.DictReader(f) if r["kind"] == "rtt" and float(r["t_s"]) >= since_s
        ]
