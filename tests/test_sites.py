"""Two cells and two edge sites in a run (docs/multipath.md): what the scenarios set and refuse, which
processes a site kill takes down, the figures and report rows of a drone on two paths, and a flight of
it with real cells: load on one cell, a whole site killed, the other cell out."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import pytest

from dynqos.common.config import ZenohConfig
from dynqos.common.errors import ConfigError
from dynqos.common.messages import SupervisorStatus
from dynqos.common.modes import ControlSource, Flow, SupervisorState
from dynqos.experiment.processes import Processes, flow_ports
from dynqos.experiment.sites import site_configs, site_processes, with_two_paths
from dynqos.plan.faults import Fault
from dynqos.plan.recording import Recording
from dynqos.plan.scenario import builtin_scenario, scenario_config
from dynqos.reports.multipath import multipath_lines, path_figures
from dynqos.reports.summary import _cpu
from tests.flights import run_file

MS = 1_000_000


def test_dual_and_single_homed_fly_the_same_timeline_and_only_dual_has_site_b() -> None:
    dual, single = builtin_scenario("dual-homed"), builtin_scenario("single-homed")
    assert (dual.sites, single.sites) == (2, 1)
    assert {(f.kind, f.site) for f in dual.faults} == {
        ("background", "a"), ("background", "b"), ("site_kill", "a"), ("cell_outage", "b")
    }  # fmt: skip
    same = [(f.at_s, f.kind, f.duration_s) for f in dual.faults if f.site == "a"]
    assert same == [(f.at_s, f.kind, f.duration_s) for f in single.faults]
    assert dual.duration_s == single.duration_s


def test_what_two_sites_need_is_refused_plainly() -> None:
    single = builtin_scenario("single-homed")
    with pytest.raises(ConfigError, match="site b needs sites = 2"):
        replace(single, faults=(Fault(at_s=1, kind="cell_outage", site="b"),))
    with pytest.raises(ConfigError, match='"links" or "camara"'):
        replace(builtin_scenario("dual-homed"), qos_backend="nef")
    with pytest.raises(ConfigError, match="1, or 2"):
        replace(single, sites=3)
    with pytest.raises(ConfigError, match="simulated drones"):
        replace(builtin_scenario("dual-homed"), vehicle="px4")
    fleet = replace(builtin_scenario("fleet-arbiter"), sites=2, faults=(Fault(at_s=1, kind="site_kill"),))
    assert fleet.fleet  # a fleet on two sites, with a site fault, is a scenario


def test_site_b_gets_its_own_router_linked_to_a_and_the_drone_a_path_through_each_cell() -> None:
    config = scenario_config(
        builtin_scenario("dual-homed"), zenoh=ZenohConfig(**flow_ports()), fc_port=1, gcs_port=2
    )
    a, b = site_configs(config, ZenohConfig(**flow_ports()))
    assert (a.mpc.site, b.mpc.site) == ("a", "b")
    assert (a.qos.site, b.qos.site) == ("a", "b")  # each site's agent, active in its own site
    assert b.zenoh.router_links == (f"tcp/127.0.0.1:{a.zenoh.default_port}",)
    _, relayed = site_configs(config, ZenohConfig(**flow_ports()), link_port=4242)  # a path_partition's relay
    assert relayed.zenoh.router_links == ("tcp/127.0.0.1:4242",)
    assert b.zenoh.default_port != a.zenoh.default_port
    assert b.cell.seed != a.cell.seed  # the two cells' jitter is not one
    cells = {
        site: {"bearers": {"uav1-default": {"port": 100 + i}, "uav1-priority": {"port": 200 + i}}}
        for i, site in enumerate(("a", "b"))
    }
    drone = with_two_paths(a, cells)
    assert [(p.name, p.connect_default, p.connect_priority) for p in drone.onboard.paths] == [
        ("a", "127.0.0.1:100", "127.0.0.1:200"), ("b", "127.0.0.1:101", "127.0.0.1:201")
    ]  # fmt: skip
    assert (drone.onboard.connect_default, drone.onboard.connect_priority) == ("", "")


def test_a_site_kill_takes_the_sites_edge_not_the_cells_nor_the_other_site(tmp_path: Path) -> None:
    procs = Processes(tmp_path / "x.toml", tmp_path)
    for name in (
        "router",
        "cell",
        "qos",
        "planner",
        "mpc",
        "mpc-1",
        "detector",
        "record",
        "vehicle",
        "onboard",
        "router-b",
        "cell-b",
        "qos-b",
        "planner-b",
        "mpc-b",
        "mpc-1-b",
        "detector-b",
    ):
        procs.procs[name] = None  # type: ignore[assignment]  # names only: nothing is started
    assert site_processes(procs, "a") == ["router", "qos", "planner", "mpc", "mpc-1", "detector"]
    assert site_processes(procs, "b") == ["router-b", "qos-b", "planner-b", "mpc-b", "mpc-1-b", "detector-b"]
    procs.down.add("mpc")
    assert "mpc" not in site_processes(procs, "a")


def _status(seq: int, t_ms: int, **fields: object) -> SupervisorStatus:
    return SupervisorStatus(
        uav="uav1", seq=seq, stamp_ns=t_ms * MS, state=SupervisorState.Q1, flow=Flow.DEFAULT,
        camera_rate_factor=1.0, control_source=ControlSource.EDGE, camera_flow=Flow.DEFAULT, latency="LL",
        risk="LR", watchdog=False, t_cam_ms=None, t_cc_ms=None, spaciousness_m=None, p_cam=0.0, p_cc=0.0,
        p_lat=0.0, p_cs=0.0, prev_state=SupervisorState.Q1, cause="", changed_ns=0, **fields,
    )  # fmt: skip


def test_the_figures_of_a_drone_on_two_paths_count_from_the_flights_start() -> None:
    Q1, Q2, Q3 = SupervisorState.Q1, SupervisorState.Q2, SupervisorState.Q3
    statuses = [
        _status(1, 0, site_wins=(("a", 5),), duplicates=7, rtt_samples_ms=(99.0,)),  # before t0: not counted
        _status(2, 1000, site_wins=(("a", 9), ("b", 1)), duplicates=10, camera_path="a",
                rtt_samples_ms=(10.0, 12.0), path_rtt_samples_ms=(("a", (10.0, 13.0)), ("b", (12.0,))),
                path_states=(("a", Q1, Flow.DEFAULT), ("b", Q3, Flow.PRIORITY))),
        _status(3, 2000, site_wins=(("a", 10), ("b", 8)), duplicates=20, camera_path="b",
                rtt_samples_ms=(30.0,), path_rtt_samples_ms=(("a", (40.0,)), ("b", (30.0, 31.0))),
                path_states=(("a", Q2, Flow.PRIORITY), ("b", Q2, Flow.PRIORITY))),
        _status(4, 3000, site_wins=(("a", 10), ("b", 13)), duplicates=25, camera_path="b"),
    ]  # fmt: skip
    m = path_figures(
        statuses, t0_ns=500 * MS, loaded=[(500 * MS, 2500 * MS)], faulted=[(800 * MS, 1500 * MS)]
    )
    assert m is not None
    assert m["commands_won"] == {"a": 1, "b": 12}
    assert m["duplicates"] == 15
    assert m["rtt_ms_winner"]["n"] == 3
    assert m["rtt_ms_winner_loaded"] == {"n": 1, "p50": 30.0, "p95": 30.0, "p99": 30.0}  # outside the fault
    assert m["rtt_ms_winner_faulted"]["n"] == 2
    assert m["rtt_ms_by_path"]["a"]["n"] == 3
    assert m["rtt_ms_by_path"]["b"]["n"] == 3
    assert m["camera_path_s"] == {"a": 1.0, "b": 1.0}
    assert m["priority_s_by_path"] == {"a": 1.0, "b": 2.0}  # each path's own PFSM's flow
    summary = {"scenario": "dual-homed", "ok": True, "multipath": m, "fallback_flown_s": 0.0}
    summary |= {"uav_delivered_mbps": 50.2, "bg_delivered_mbps": 30.0}
    summary["cells"] = {"b": {"uav_delivered_mbps": 0.4, "bg_delivered_mbps": None}}
    rows = multipath_lines([summary])
    winner = next(row for row in rows if row.startswith("| dual-homed | 1 | 12 / "))
    assert "| 30 / 30 / 30 | 11 / " in winner
    assert "| 0.08 / 0.92 | 1.0 / 2.0 | 15 | 0.0 |" in winner
    assert rows[-1] == "| dual-homed | 1 | 50.2 / 30.0 | 0.4 / - |"  # each cell's uplink
    assert multipath_lines([{"scenario": "baseline", "ok": True}]) == []


@pytest.mark.slow
@pytest.mark.integration
@pytest.mark.timeout(300)
def test_a_dual_homed_drone_flies_through_load_a_site_kill_and_a_cell_outage_without_its_fallback(
    tmp_path: Path,
) -> None:
    """dual-homed's timeline, shortened: load on cell A from 4 s, the link between the sites' routers cut
    from 5 s for 3 s, every process of site A SIGKILLed at 10 s (restarted 3 s later), cell B out from
    18 s for 3 s; real cells, routers, MPCs, planners."""
    scenario = tmp_path / "dh.toml"
    scenario.write_text(
        '[scenario]\nname = "dh"\nsites = 2\nduration_s = 24\nbg_start_s = -1\n'
        + "".join(
            f'[[scenario.faults]]\nat_s = {at}\nkind = "{kind}"\nsite = "{site}"\nduration_s = {dur}\n'
            for at, kind, site, dur in ((4, "background", "a", 19), (5, "path_partition", "a", 3),
                                        (10, "site_kill", "a", 3), (18, "cell_outage", "b", 3))
        )
    )  # fmt: skip
    out = tmp_path / "run"
    result = run_file(scenario, out)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "dh" / "summary.json").read_text())
    onboard = (out / "dh" / "logs" / "onboard.log").read_text()
    assert summary["ok"], summary["failure"]
    assert summary["fallbacks"]["in_flight"] == 0, onboard[-3000:]
    assert summary["fallback_flown_s"] == 0.0
    partition, kill, outage = (
        f for f in summary["faults"] if f["kind"] in ("path_partition", "site_kill", "cell_outage")
    )
    assert "the link between the sites' routers cut (1 connection(s))" in partition["notes"]
    assert "site a: killed router, qos, planner, mpc, detector" in kill["notes"]
    assert not partition["fallback"]
    assert not kill["fallback"]
    assert not outage["fallback"]
    m = summary["multipath"]
    assert m["commands_won"]["a"] > 0, m  # both sites flew the drone
    assert m["commands_won"]["b"] > 0, m
    assert m["duplicates"] > 0
    assert set(m["rtt_ms_by_path"]) == {"a", "b"}
    assert "first command from site b" in onboard
    gaps = re.findall(r"max_command_gap_ms=([0-9.]+)", onboard)
    assert gaps, onboard[-3000:]
    assert float(gaps[-1]) < 150.0, onboard[-3000:]  # never a gap between applied Commands of T_wd
    assert (out / "dh" / "site-b" / "cell.csv").is_file()  # cell B kept its own record
    assert summary["cells"]["b"]["uav_delivered_mbps"] > 0  # its counters: States and statuses at least
    # each site's agent asked its own operator; none of their sessions is left, the killed site's neither
    operators = summary["qos_network"]["operators"]
    # each path asked by its own PFSM: the circle's high risk (q2) sends both paths to priority
    assert operators["a"]["created"] >= 1, operators
    assert operators["b"]["created"] >= 1, operators
    assert "supervisor, path a: q1 -> q2" in onboard, onboard[-3000:]
    assert m["priority_s_by_path"]["a"] > 0, m
    assert set(m["priority_s_by_path"]) == {"a", "b"}, m
    assert (operators["a"]["open_at_end"], operators["b"]["open_at_end"]) == (0, 0), operators
    assert "## Two paths, two sites" in (out / "report.md").read_text()


def test_the_flights_cpu_leaves_the_start_out_and_counts_a_restarted_process_from_its_restart() -> None:
    rec = Recording(cpu_s_t0={"onboard": 2.0, "router": 5.0})
    rec.cpu_s = {"onboard": 6.5, "router": 1.5, "mpc-b": 3.0}  # the router was killed and restarted
    assert _cpu(rec)["cpu_s_flight"] == {"onboard": 4.5, "router": 1.5, "mpc-b": 3.0}
    assert _cpu(Recording(cpu_s={"onboard": 1.0})) == {"cpu_s": {"onboard": 1.0}}  # the start never read
