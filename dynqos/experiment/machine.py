"""How busy the machine is, read from the kernel's own CPU accounting while a flight is recorded
(dynqos/reports/machine.py judges a flight by it: the reasons are there).

The machine is what this process may use: its cores are those it may run on (its CPU affinity), and
where its control group has a CPU quota (dynqos/experiment/cgroup.py) that quota is the machine.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

from dynqos.experiment.cgroup import QuotaGroup, find_quota, read_group
from dynqos.plan.recording import CpuTimes

PROC_STAT = Path("/proc/stat")


def parse_cpu_line(text: str, cpus: frozenset[int] | None = None) -> CpuTimes:
    """The aggregate `cpu` line of /proc/stat (or the sum of the `cpuN` lines of `cpus`): user nice
    system idle iowait irq softirq steal [guest ...]; guest time is already counted in user and nice,
    so only the first eight fields add up."""
    names = {"cpu"} if cpus is None else {f"cpu{n}" for n in cpus}
    ticks = [0] * 8
    found = False
    for line in text.splitlines():
        fields = line.split()
        if fields and fields[0] in names:
            found = True
            for i, value in enumerate(fields[1:9]):
                ticks[i] += int(value)
    if not found:
        raise ValueError("no aggregate cpu line in /proc/stat" if cpus is None else f"no line of cpus {cpus}")
    total = sum(ticks)
    return CpuTimes(busy=total - ticks[3] - ticks[4], total=total, steal=ticks[7])


def usable_cpus() -> frozenset[int] | None:
    """The cores this process may run on, where they are fewer than the host's (None: all of them)."""
    try:
        allowed = frozenset(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None
    return None if len(allowed) >= (os.cpu_count() or 0) else allowed


@functools.cache
def own_machine() -> tuple[frozenset[int] | None, QuotaGroup | None]:
    """This process's cores (None: all) and quota group (None: none): they hold for its life."""
    return usable_cpus(), find_quota()


def read_cpu_times(
    path: Path = PROC_STAT, cpus: frozenset[int] | None = None, quota: QuotaGroup | None = None
) -> CpuTimes | None:
    """Now's CpuTimes of `cpus` (None: all) with `quota`'s reading, or None where there is no
    /proc/stat (the figures are then left out). A flight reads its own machine (`own_machine`)."""
    try:
        times = parse_cpu_line(path.read_text(encoding="ascii"), cpus)
    except (OSError, ValueError):
        return None
    if quota is None:
        return times
    return CpuTimes(times.busy, times.total, times.steal, read_group(quota))


def usable_core_count() -> int:
    """How many cores this process may use (its affinity; the host's count where it is all of them)."""
    cpus = own_machine()[0]
    return len(cpus) if cpus is not None else os.cpu_count() or 1


SIZED_FOR_CORES = 2  # the scenarios' processes were sized for a machine of two cores


def machine_said() -> tuple[str, bool]:
    """What a run says of its machine before it flies, and whether it has less than the scenarios
    were sized for (its flights then likely starve, and their summaries will say so)."""
    cores, group = usable_core_count(), own_machine()[1]
    quota = float(cores) if group is None else min(cores, group.cores)
    text = f"{cores} core{'' if cores == 1 else 's'}" + (
        f", a CPU quota of {group.cores:.2f} cores" if group is not None else ""
    )
    return text, quota < SIZED_FOR_CORES
