"""The paper's central claim, flown: without QoS the drone's latency climbs once the cell is loaded; with
dynamic QoS the supervisor moves to the priority flow because of that latency, within a second, and the
latency stays near the baseline.

Both flights hover at the same point (the no-QoS scenario's mission), so the QoS mode is the only
difference, and the dynamic one meets the load at medium risk: its move to the priority flow can only
be the latency's doing. It fails if the supervisor stops reacting to high latency (rho2 out of reach),
if the priority bearer loses its weight, or if the drone offers no more than its fair share of the
loaded cell (the camera sized on views it does not fly).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from dynqos.common.config import CellConfig
from dynqos.runner import run_scenario
from dynqos.scenario import builtin_scenario

FAIR_SHARE_MBPS = CellConfig().uplink_mbps / 2  # the drone and one background user, equal weights


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(420)
def test_without_qos_latency_climbs_and_dynamic_qos_switches_on_it_and_holds(tmp_path: Path) -> None:
    noqos = replace(builtin_scenario("bg-noqos"), duration_s=20.0, bg_start_s=10.0)
    dynamic = replace(builtin_scenario("bg-dynqos-hover"), duration_s=20.0, bg_start_s=10.0)
    assert (dynamic.mission, dynamic.bg_mbps) == (noqos.mission, noqos.bg_mbps)  # only the QoS differs

    without = run_scenario(noqos, tmp_path, progress=False)
    assert without["ok"], without["failure"]
    assert without["camera_fps"]["baseline"] >= 0.9 * noqos.camera_fps  # the machine kept the rate up
    assert without["uav_offered_mbps"] > FAIR_SHARE_MBPS  # the drone asks for more than its share...
    assert without["uav_delivered_mbps"] < without["uav_offered_mbps"]  # ...and does not get it
    assert without["uav_delivered_mbps"] <= 1.02 * FAIR_SHARE_MBPS
    baseline, loaded = without["rtt_ms"]["baseline"], without["rtt_ms"]["loaded"]
    print(f"no QoS: RTT {baseline['mean']:.1f} ms before the load, p95 {loaded['p95']:.1f} ms under it")
    assert loaded["p95"] >= 3 * baseline["mean"]

    with_qos = run_scenario(dynamic, tmp_path, progress=False)
    assert with_qos["ok"], with_qos["failure"]
    cause = with_qos["first_qos_switch_cause"]
    switch_s = with_qos["first_qos_switch_after_bg_s"]
    baseline, loaded = with_qos["rtt_ms"]["baseline"], with_qos["rtt_ms"]["loaded"]
    print(f"dynamic QoS: switch {switch_s} s ({cause}); RTT {baseline['mean']:.1f}, {loaded['mean']:.1f} ms")
    assert cause is not None
    assert "HL" in cause
    assert not cause.startswith("before the load")
    assert switch_s <= 1.0
    assert loaded["mean"] <= 1.3 * baseline["mean"]
