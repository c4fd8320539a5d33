"""How busy the machine was during a flight (dynqos/experiment/machine.py): read from the kernel's
/proc/stat, figured per second, and said in the report, starved or not."""

from __future__ import annotations

from pathlib import Path

import pytest

from dynqos.experiment.machine import parse_cpu_line, read_cpu_times
from dynqos.plan.faults import Fault, FaultWindow
from dynqos.plan.recording import CpuTimes, Recording
from dynqos.reports.machine import busy_share, describe, judge, machine_figures, own_load_spans

STAT = """cpu  237491 3186 34901 606039 2155 0 5747 4819 0 0
cpu0 82231 1602 14105 343587 316 0 2775 2466 0 0
intr 12345
"""


def test_the_aggregate_line_counts_idle_and_iowait_as_not_busy_and_steal_as_busy() -> None:
    times = parse_cpu_line(STAT)
    assert times.total == 237491 + 3186 + 34901 + 606039 + 2155 + 0 + 5747 + 4819
    assert times.busy == times.total - 606039 - 2155
    assert times.steal == 4819
    with pytest.raises(ValueError, match="no aggregate cpu line"):
        parse_cpu_line("cpu0 1 2 3 4\n")


def test_this_kernels_proc_stat_reads_and_moves(tmp_path: Path) -> None:
    first = read_cpu_times()
    assert first is not None
    assert 0 < first.busy < first.total
    assert read_cpu_times(tmp_path / "missing") is None


def test_busy_share_between_two_readings() -> None:
    assert busy_share(CpuTimes(100, 1000), CpuTimes(250, 1200)) == pytest.approx(0.75)
    assert busy_share(CpuTimes(100, 1000), CpuTimes(100, 1000)) is None


def _flight(shares: list[float]) -> list[tuple[float, CpuTimes]]:
    """One reading a second, each second `share` busy (200 ticks: two cores at 100 Hz)."""
    samples, busy, total = [(0.0, CpuTimes(0, 0))], 0, 0
    for t, share in enumerate(shares, 1):
        busy, total = busy + round(200 * share), total + 200
        samples.append((float(t), CpuTimes(busy, total)))
    return samples


def test_a_flight_with_headroom_is_not_starved_and_one_without_is() -> None:
    calm = machine_figures(_flight([0.5] * 20 + [0.95] * 3), cores=2)
    assert calm is not None
    assert calm["busy_share"] == pytest.approx((0.5 * 20 + 0.95 * 3) / 23)
    assert calm["busy_share_max_1s"] == pytest.approx(0.95)
    assert (calm["seconds_above_85"], calm["seconds_sampled"], calm["starved"]) == (3, 23, False)
    busy = machine_figures(_flight([0.5] * 20 + [0.9] * 4), cores=2)
    assert busy is not None
    assert busy["starved"]
    assert "STARVED" in describe(busy)
    assert "STARVED" not in describe(calm)
    assert machine_figures(_flight([]), cores=2) is None
    assert describe(None) == "machine: not measured (no /proc/stat)"
    # A starved flight is not a result: not ok, and its failure says why; a calm one keeps its verdict.
    ok, failure = judge(True, "", busy)
    assert not ok
    assert failure.startswith("starved: the machine was above 85% busy for 4 of 24 s")
    assert judge(True, "", calm) == (True, "")
    assert judge(False, "the MPC crashed", busy) == (False, "the MPC crashed")  # the first cause stays
    assert judge(True, "", None) == (True, "")


def test_busy_seconds_while_the_flights_own_faults_load_the_machine_do_not_starve_it() -> None:
    """A faults flight restarts services (imports, sessions: a core for a second or two) and floods the
    detector: those busy seconds are kept apart and said, and only the others can starve the flight."""
    shares = [0.5] * 20 + [0.95] * 4 + [0.5] * 10 + [0.95] * 1
    own = machine_figures(_flight(shares), cores=2, own_load=[(20.5, 23.5)])
    assert own is not None
    assert (own["seconds_above_85"], own["seconds_above_85_own_faults"], own["starved"]) == (5, 4, False)
    assert own["seconds_above_85_at_s"] == [21.0, 22.0, 23.0, 24.0, 35.0]
    assert "5 of 35 s above 85%, 4 of them while the flight's own faults loaded it" in describe(own)
    assert judge(True, "", own) == (True, "")
    unexplained = machine_figures(_flight(shares), cores=2)  # the same seconds, no restart then
    assert unexplained is not None
    assert unexplained["starved"]
    more = machine_figures(_flight(shares + [0.95] * 3), cores=2, own_load=[(20.5, 23.5)])
    ok, failure = judge(True, "", more)
    assert not ok
    assert "busy for 4 of 38 s besides 4 while its own faults loaded it" in failure


def test_own_load_spans_are_the_faults_restarts_in_seconds_into_the_flight() -> None:
    s = 1_000_000_000
    window = FaultWindow(Fault(at_s=30, kind="mpc_kill", duration_s=3), 0.0, 130 * s)
    window.restarts.append((133 * s, 134 * s + s // 2))  # began at the fault's end, ready 1.5 s later
    rec = Recording(faults=[window])
    assert own_load_spans(rec) == []  # a recording without its flight's start has no flight seconds
    rec.flight_start_ns = 100 * s
    assert own_load_spans(rec) == [(33.0, 35.5)]  # ready at 34.5 s, and a second of warming up


def _stolen(shares: list[float], steal: float) -> list[tuple[float, CpuTimes]]:
    """As `_flight`, with `steal` of every second taken by the hypervisor (part of the busy share)."""
    samples = _flight(shares)
    return [(t, CpuTimes(c.busy, c.total, round(200 * steal * t))) for t, c in samples]


def test_a_host_that_takes_the_cores_is_said_and_the_verdict_stands() -> None:
    """29% steal was seen here in a CI run whose flights failed on latency; 2% is this host's usual."""
    usual = machine_figures(_stolen([0.45] * 30, 0.02), cores=2)
    taken = machine_figures(_stolen([0.6] * 30, 0.29), cores=2)
    assert usual is not None
    assert taken is not None
    assert usual["steal_share"] == pytest.approx(0.02, abs=1e-3)
    assert taken["steal_share"] == pytest.approx(0.29, abs=1e-3)
    assert (usual["stolen"], usual["starved"]) == (False, False)
    assert (taken["seconds_above_85"], taken["stolen"], taken["starved"]) == (0, True, False)
    assert "29% taken by the hypervisor" in describe(taken)
    assert "STOLEN" in describe(taken)
    assert "STOLEN" not in describe(usual)
    assert judge(True, "", taken) == (True, "")  # a flight that held its bounds anyway is a result
    just = machine_figures(_stolen([0.5] * 30, 0.10), cores=2)
    assert just is not None
    assert not just["stolen"]  # the bound itself is not stolen
