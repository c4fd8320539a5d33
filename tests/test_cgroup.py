"""A container's CPU quota as a flight's machine (dynqos/experiment/cgroup.py, machine.py): found in either
cgroup version, read from the kernel, and a flight that used its quota up is starved however idle the
host looked."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from dynqos.experiment import machine
from dynqos.experiment.cgroup import (
    QuotaGroup,
    find_quota,
    group_dir,
    parse_cpu_stat,
    parse_mountinfo,
    parse_proc_cgroup,
    parse_quota_v1,
    parse_quota_v2,
    read_group,
)
from dynqos.experiment.machine import machine_said, parse_cpu_line
from dynqos.plan.recording import CpuTimes, GroupCpu
from dynqos.reports.machine import describe, judge, machine_figures

# A v1 host (this machine's layout: cpu and cpuacct mounted apart) and a v2 container (its own group
# is the root its mount shows), as /proc/self/mountinfo says them.
MOUNTS_V1 = """31 23 0:28 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755
32 31 0:29 / {root}/cpu rw,relatime - cgroup cgroup rw,cpu
33 31 0:30 / {root}/cpuacct rw,relatime - cgroup cgroup rw,cpuacct
35 31 0:32 / {root}/memory rw,relatime - cgroup cgroup rw,memory
41 31 0:38 / {root}/unified rw,relatime - cgroup2 cgroup2 rw
"""
CGROUP_V1 = "4:memory:/process_api/x\n2:cpuacct:/ci/job\n1:cpu:/ci/job\n0::/\n"
MOUNTS_V2 = "1650 1640 0:29 /../.. {root} ro,nosuid - cgroup2 cgroup rw,nsdelegate\n"
MOUNTS_V2_NS = "1650 1640 0:29 / {root} ro,nosuid - cgroup2 cgroup rw,nsdelegate\n"


def test_the_mounts_and_groups_are_parsed_as_the_kernel_writes_them() -> None:
    mounts = parse_mountinfo(MOUNTS_V1.format(root="/sys/fs/cgroup"))
    assert [(m.point.name, m.version, sorted(m.controllers)) for m in mounts] == [
        ("cpu", 1, ["cpu", "rw"]),
        ("cpuacct", 1, ["cpuacct", "rw"]),
        ("memory", 1, ["memory", "rw"]),
        ("unified", 2, []),
    ]
    groups = parse_proc_cgroup("11:cpu,cpuacct:/docker/abc\n0::/system.slice/x.scope\n")
    assert groups == {"cpu": "/docker/abc", "cpuacct": "/docker/abc", "": "/system.slice/x.scope"}
    # a v1 container without its own cgroup namespace: its group is the mount's root
    docker = parse_mountinfo("5 1 0:3 /docker/abc /sys/fs/cgroup/cpu rw - cgroup cgroup rw,cpu,cpuacct\n")[0]
    assert group_dir(docker, "/docker/abc") == Path("/sys/fs/cgroup/cpu")
    assert group_dir(docker, "/docker/abc/inner") == Path("/sys/fs/cgroup/cpu/inner")
    assert group_dir(docker, "/docker/abcd") is None  # a sibling is not under the mount


def test_quotas_in_either_version_and_none() -> None:
    assert parse_quota_v2("150000 100000\n") == pytest.approx(1.5)
    assert parse_quota_v2("max 100000\n") is None
    assert parse_quota_v1("50000\n", "100000\n") == pytest.approx(0.5)
    assert parse_quota_v1("-1\n", "100000\n") is None
    stat = parse_cpu_stat("usage_usec 120\nnr_periods 10\nnr_throttled 3\nthrottled_usec 4500\n")
    assert stat == {"usage_usec": 120, "nr_periods": 10, "nr_throttled": 3, "throttled_usec": 4500}


def _write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def test_the_smallest_quota_from_the_own_group_up_binds_in_v2(tmp_path: Path) -> None:
    """A pod's container (no quota of its own) inside its pod's group (1.5 cores) inside the node's
    pods group (8): the pod's binds; its usage and throttled time come from its cpu.stat."""
    root = tmp_path / "fs"
    _write(root / "cpu.max", "800000 100000\n")
    _write(root / "pod" / "cpu.max", "150000 100000\n")
    _write(
        root / "pod" / "cpu.stat", "usage_usec 2000000\nnr_periods 50\nnr_throttled 7\nthrottled_usec 90000\n"
    )
    _write(root / "pod" / "ctr" / "cpu.max", "max 100000\n")
    (tmp_path / "mountinfo").write_text(MOUNTS_V2_NS.format(root=root))
    (tmp_path / "cgroup").write_text("0::/pod/ctr\n")
    quota = find_quota(tmp_path / "mountinfo", tmp_path / "cgroup")
    assert quota == QuotaGroup(cores=1.5, cpu_dir=root / "pod", usage_dir=root / "pod", version=2)
    assert read_group(quota) == GroupCpu(1.5, 2_000_000_000, 90_000_000)
    # no quota anywhere, or no cgroup readable at all: nothing to say
    (root / "pod" / "cpu.max").write_text("max 100000\n")
    (root / "cpu.max").write_text("max 100000\n")
    assert find_quota(tmp_path / "mountinfo", tmp_path / "cgroup") is None
    assert find_quota(tmp_path / "absent", tmp_path / "cgroup") is None


def test_v1_reads_the_usage_from_cpuacct_mounted_apart(tmp_path: Path) -> None:
    root = tmp_path / "fs"
    _write(root / "cpu" / "ci" / "cpu.cfs_quota_us", "133000\n")
    _write(root / "cpu" / "ci" / "cpu.cfs_period_us", "100000\n")
    _write(root / "cpu" / "ci" / "cpu.stat", "nr_periods 9\nnr_throttled 2\nthrottled_time 5000000\n")
    _write(root / "cpu" / "ci" / "job" / "cpu.cfs_quota_us", "-1\n")
    _write(root / "cpu" / "ci" / "job" / "cpu.cfs_period_us", "100000\n")
    _write(root / "cpuacct" / "ci" / "cpuacct.usage", "7000000000\n")
    (tmp_path / "mountinfo").write_text(MOUNTS_V1.format(root=root))
    (tmp_path / "cgroup").write_text(CGROUP_V1)
    quota = find_quota(tmp_path / "mountinfo", tmp_path / "cgroup")
    assert quota == QuotaGroup(1.33, root / "cpu" / "ci", root / "cpuacct" / "ci", 1)
    assert read_group(quota) == GroupCpu(1.33, 7_000_000_000, 5_000_000)
    (root / "cpuacct" / "ci" / "cpuacct.usage").unlink()  # no usage: the throttling is still said
    assert read_group(quota) == GroupCpu(1.33, None, 5_000_000)


def _quota_flight(
    used: list[float], held: list[float], host_share: float = 0.4
) -> list[tuple[float, CpuTimes]]:
    """One reading a second on two cores, the host `host_share` busy, the group under a 1-core quota
    using `used[i]` of it and held for `held[i]` s (summed over the cores) in second i."""
    samples = [(0.0, CpuTimes(0, 0, 0, GroupCpu(1.0, 0, 0)))]
    usage = throttled = busy = total = 0
    for t, (share, hold) in enumerate(zip(used, held, strict=True), 1):
        usage, throttled = usage + round(share * 1e9), throttled + round(hold * 1e9)
        busy, total = busy + round(200 * host_share), total + 200
        samples.append((float(t), CpuTimes(busy, total, 0, GroupCpu(1.0, usage, throttled))))
    return samples


def test_a_flight_that_used_its_quota_up_is_starved_on_an_idle_host() -> None:
    spent = machine_figures(_quota_flight([0.95] * 6 + [0.5] * 4, [0.3] * 6 + [0.0] * 4), cores=2)
    assert spent is not None
    assert spent["busy_share"] == pytest.approx(0.4)  # the host looked idle
    assert (spent["quota_cores"], spent["seconds_above_85"], spent["starved"]) == (1.0, 6, True)
    assert spent["quota_share"] == pytest.approx((0.95 * 6 + 0.5 * 4) / 10)
    assert spent["quota_share_max_1s"] == pytest.approx(0.95)
    assert spent["throttled_share"] == pytest.approx(0.3 * 6 / (2 * 10))
    assert spent["throttled"]
    line = describe(spent)
    assert "a CPU quota of 1.00 cores, 77% of it used, 9% of the cores' time held by it" in line
    assert "STARVED" in line
    assert "THROTTLED" in line
    ok, failure = judge(True, "", spent)
    assert not ok
    assert failure.startswith("starved: the machine (or its CPU quota) was above 85% busy for 6 of 10 s")
    room = machine_figures(_quota_flight([0.5] * 10, [0.0] * 10), cores=2)
    assert room is not None
    assert (room["starved"], room["throttled"], room["throttled_share"]) == (False, False, 0.0)
    assert "THROTTLED" not in describe(room)
    assert "quota_cores" not in (
        machine_figures([(0.0, CpuTimes(0, 0)), (1.0, CpuTimes(1, 2))], cores=2) or {}
    )


def test_only_the_usable_cores_lines_are_summed() -> None:
    stat = "cpu  30 0 0 70 0 0 0 0\ncpu0 10 0 0 40 0 0 0 0\ncpu1 20 0 0 30 0 0 0 0\n"
    assert parse_cpu_line(stat) == CpuTimes(busy=30, total=100)
    assert parse_cpu_line(stat, frozenset({1})) == CpuTimes(busy=20, total=50)
    with pytest.raises(ValueError, match="no line of cpus"):
        parse_cpu_line(stat, frozenset({7}))


def test_a_run_says_its_machine_first_and_warns_below_two_cores(monkeypatch: pytest.MonkeyPatch) -> None:
    """`dynqos demo` logs it before the first scenario: cores, quota, and a warning under two."""
    group = QuotaGroup(cores=1.33, cpu_dir=Path("/x"), usage_dir=None, version=2)
    for cpus, quota, said in [
        (frozenset({0, 1}), None, ("2 cores", False)),
        (frozenset({0, 1}), group, ("2 cores, a CPU quota of 1.33 cores", True)),
        (frozenset({3}), None, ("1 core", True)),
        (frozenset(range(8)), replace(group, cores=4.0), ("8 cores, a CPU quota of 4.00 cores", False)),
    ]:
        monkeypatch.setattr(machine, "own_machine", lambda c=cpus, q=quota: (c, q))
        assert machine_said() == said


V1_CPU = Path("/sys/fs/cgroup/cpu")
V1_CPUACCT = Path("/sys/fs/cgroup/cpuacct")


@contextlib.contextmanager
def _v1_group(name: str, quota_us: int, period_us: int) -> Iterator[tuple[Path, Path]]:
    """A v1 cpu (and cpuacct) group of this test's own, with a quota; removed after."""
    cpu, acct = V1_CPU / name, V1_CPUACCT / name
    try:
        cpu.mkdir()
    except OSError as exc:
        pytest.skip(f"cannot make a v1 cpu group here: {exc}")
    try:
        acct.mkdir()
        try:
            (cpu / "cpu.cfs_period_us").write_text(str(period_us))
            (cpu / "cpu.cfs_quota_us").write_text(str(quota_us))
            yield cpu, acct
        finally:
            acct.rmdir()
    finally:
        cpu.rmdir()


@pytest.mark.timeout(30)
def test_the_kernel_holds_a_busy_process_to_its_quota_and_says_so(tmp_path: Path) -> None:
    """A busy loop in a group of a fifth of a core, read as a flight reads its machine: the group used
    its quota, was held the rest of the time, and the flight is starved and throttled."""
    if os.geteuid() != 0 or not (V1_CPU / "cpu.cfs_quota_us").exists() or not V1_CPUACCT.is_dir():
        pytest.skip("needs root and the v1 cpu and cpuacct controllers to make a group with a CPU quota")
    with _v1_group(f"dynqos-test-{os.getpid()}", quota_us=2000, period_us=10000) as (cpu, acct):
        quota = QuotaGroup(cores=0.2, cpu_dir=cpu, usage_dir=acct, version=1)
        loop = "import time\nend = time.monotonic() + 20\nwhile time.monotonic() < end: pass\n"
        busy = subprocess.Popen([sys.executable, "-c", loop])
        try:
            (cpu / "cgroup.procs").write_text(str(busy.pid))
            (acct / "cgroup.procs").write_text(str(busy.pid))
            samples = []
            start = time.monotonic()
            for _ in range(6):  # five one-second shares
                group = read_group(quota)
                assert group is not None
                samples.append((time.monotonic() - start, CpuTimes(0, 0, 0, group)))
                time.sleep(1.0)  # the kernel's accounting is what is read: seconds of it, not an event
        finally:
            busy.kill()  # a process that has ended leaves its group, which can then go
            busy.wait(timeout=10)
    figures = machine_figures(samples, cores=os.cpu_count())
    assert figures is not None
    assert figures["quota_cores"] == pytest.approx(0.2)
    assert figures["quota_share"] > 0.85  # it used its fifth of a core (1.0 on an idle machine)
    assert figures["quota_share_max_1s"] > 0.85
    assert figures["starved"]
    assert figures["seconds_above_85"] >= 4  # of 5 (a busy machine may take a second of it)
    # held up to 80% of each second on one core (40% of two cores' time on an idle machine)
    assert 0.05 < figures["throttled_share"] <= 0.8 / (os.cpu_count() or 1) + 0.05
    assert figures["throttled"]
