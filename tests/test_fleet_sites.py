"""A fleet on two sites (docs/fleet.md, docs/multipath.md): each drone on two paths, each cell with a pair
of bearers per drone forwarded to its own site's router, and a flight of it where site A is killed."""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from dynqos.common.config import ZenohConfig
from dynqos.experiment.processes import flow_ports
from dynqos.experiment.sites import site_configs, with_site_b_bearers, with_two_paths
from dynqos.plan.scenario import builtin_scenario, fleet_configs
from tests.flights import fly_for_behaviour, run_file


def test_cell_b_forwards_each_drone_s_bearers_to_site_b_s_router_and_each_drone_dials_both_cells() -> None:
    scenario = builtin_scenario("fleet-dual-homed")
    zenoh_a, zenoh_b = ZenohConfig(**flow_ports()), ZenohConfig(**flow_ports())
    shared, drones = fleet_configs(scenario, zenoh=zenoh_a, fc_base=20000, gcs_port=20010)
    a, b = site_configs(shared, zenoh_b)
    b = with_site_b_bearers(b, a.zenoh)
    assert len(b.cell.bearers) == 2 * len(drones)  # a default and a priority bearer per drone
    for ours, theirs in zip(b.cell.bearers, a.cell.bearers, strict=True):
        assert ours.name == theirs.name
        port = int(ours.target.rpartition(":")[2])
        want = zenoh_b.priority_port if ours.name.endswith("-priority") else zenoh_b.default_port
        assert port == want, (ours, theirs)
    assert (a.qos.site, b.qos.site) == ("a", "b")  # each site's agent and arbiter, its own operator's
    cells = {
        site: {
            "control_port": 1,
            "bearers": {bb.name: {"port": 3000 + i} for i, bb in enumerate(c.cell.bearers)},
        }
        for site, c in (("a", a), ("b", b))
    }
    config = with_two_paths(drones["uav3"], cells)
    assert [p.name for p in config.onboard.paths] == ["a", "b"]
    own = cells["b"]["bearers"]["uav3-default"]["port"]
    assert config.onboard.paths[1].connect_default == f"127.0.0.1:{own}"  # uav3's own bearer in cell B


def _fly(out: Path) -> dict[str, Any]:
    """fleet-dual-homed's timeline, shortened: the load on cell A from 8 s, site A killed at 12 s for 3 s,
    20 s in all (the shipped file's text, its times changed)."""
    text = (resources.files("dynqos") / "scenarios" / "fleet-dual-homed.toml").read_text()
    for old, new in (("bg_start_s = 20", "bg_start_s = 8"), ("at_s = 30", "at_s = 12"),
                     ("duration_s = 45", "duration_s = 20")):  # fmt: skip
        assert old in text, old
        text = text.replace(old, new)
    scenario = out.parent / f"{out.name}.toml"
    scenario.write_text(text)
    result = run_file(scenario, out)
    summary: dict[str, Any] = json.loads((out / "fleet-dual-homed" / "summary.json").read_text())
    assert result.returncode == (0 if summary["ok"] else 1), result.stderr[-3000:]
    return summary


def _check(summary: dict[str, Any], out: Path) -> None:
    (kill,) = summary["faults"]
    assert kill["kind"] == "site_kill"
    assert "site a: killed router" in kill["notes"][0], kill
    assert kill["fell_back"] == [], kill
    assert summary["checks"]["no_fallback_in_faults"] is True
    for uav, drone in summary["drones"].items():
        said = (
            f"{uav}: time in each state {drone['states_time_s']}, largest setpoint gap "
            f"{drone['setpoint_gap_max_ms']} ms, multipath {drone['multipath']}; machine {summary['machine']}"
        )
        assert drone["fallback_entered"] is False, said  # the whole flight, not the kill's window alone
        assert drone["fallback_flown_s"] == 0.0, said
        m = drone["multipath"]
        assert m["commands_won"].get("b", 0) > 0, (uav, m)  # site b flew it, at the least while A was down
        assert set(m["rtt_ms_by_path"]) == {"a", "b"}, uav
    operators = summary["qos_network"]["operators"]
    assert operators["a"]["created"] >= 1, operators  # the high-risk drones asked operator A...
    assert operators["b"]["created"] >= 1, operators  # ...and operator B, each by its own path
    assert (operators["a"]["open_at_end"], operators["b"]["open_at_end"]) == (0, 0), operators


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(600)  # a flight whose cores were not its own is flown again
def test_a_dual_homed_fleet_flies_through_a_site_kill_without_a_fallback(tmp_path: Path) -> None:
    """fleet-dual-homed, shortened: the arbiter's fleet on two paths each, site A's every process
    SIGKILLed under load: no drone falls back, site b flies each, no QoD session is left at either
    operator."""
    fly_for_behaviour(_fly, tmp_path, _check)
