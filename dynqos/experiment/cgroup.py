"""The CPU quota of the control group this process runs in, and how much of it the group used.

A flight may run in a container whose control group has a CPU quota (Docker's `--cpus`, a Kubernetes
CPU limit, a CI runner). The kernel then lets the group's processes run `quota` microseconds in every
`period` and holds every one of them until the next period once they are spent: a stop of up to the
rest of the period (tens of milliseconds with the usual 100 ms) that lands in a flight's round trips
as if the network had caused it. /proc/stat speaks for the host's cores and may look idle meanwhile.
So the flight's machine figures (dynqos/experiment/machine.py) also read the group: the quota in cores,
the CPU time the group used and the time it was held (throttled).

Both cgroup versions are read: v2's `cpu.max` and `cpu.stat`; v1's `cpu.cfs_quota_us`,
`cpu.cfs_period_us` and `cpu.stat`, with the usage from the `cpuacct` controller. The quota that binds
is the smallest from this process's group up to the root its mount shows (a container sees its own
group as the root). Parsing is pure; `find_quota` and `read_group` read the files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dynqos.plan.recording import GroupCpu

MOUNTINFO = Path("/proc/self/mountinfo")
PROC_CGROUP = Path("/proc/self/cgroup")


@dataclass(frozen=True, slots=True)
class QuotaGroup:
    """The group whose quota binds: its cores (quota / period), its cpu directory, and the directory
    its CPU usage is read from (v1's cpuacct; None where that controller is not mounted)."""

    cores: float
    cpu_dir: Path
    usage_dir: Path | None
    version: int


@dataclass(frozen=True, slots=True)
class Mount:
    root: str  # the group the mount shows as its root
    point: Path  # where it is mounted
    version: int
    controllers: frozenset[str]


def parse_mountinfo(text: str) -> list[Mount]:
    """The cgroup mounts of /proc/self/mountinfo (fields: id parent dev root point options ... - type
    source superoptions; v1's controllers are in the superoptions)."""
    mounts = []
    for line in text.splitlines():
        left, sep, right = line.partition(" - ")
        fields, tail = left.split(), right.split()
        if not sep or len(fields) < 5 or len(tail) < 3 or tail[0] not in ("cgroup", "cgroup2"):
            continue
        version = 2 if tail[0] == "cgroup2" else 1
        controllers = frozenset() if version == 2 else frozenset(tail[2].split(","))
        mounts.append(Mount(root=fields[3], point=Path(fields[4]), version=version, controllers=controllers))
    return mounts


def parse_proc_cgroup(text: str) -> dict[str, str]:
    """This process's group per controller ("" for v2's unified hierarchy) from /proc/self/cgroup."""
    groups: dict[str, str] = {}
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        for controller in controllers.split(",") if controllers else [""]:
            groups[controller] = path
    return groups


def group_dir(mount: Mount, path: str) -> Path | None:
    """Where `path` (a group, as /proc/self/cgroup names it) lies under `mount`; None if outside it."""
    root = mount.root.rstrip("/")
    if path != root and not path.startswith(root + "/"):
        return None
    return mount.point / path[len(root) :].lstrip("/")


def parse_quota_v2(cpu_max: str) -> float | None:
    """v2's cpu.max, "QUOTA PERIOD" or "max PERIOD", in cores (None: no quota)."""
    fields = cpu_max.split()
    if len(fields) != 2 or fields[0] == "max" or int(fields[1]) <= 0:
        return None
    return int(fields[0]) / int(fields[1])


def parse_quota_v1(quota_us: str, period_us: str) -> float | None:
    """v1's cpu.cfs_quota_us and cpu.cfs_period_us, in cores (None: no quota, -1)."""
    quota, period = int(quota_us), int(period_us)
    return None if quota <= 0 or period <= 0 else quota / period


def parse_cpu_stat(text: str) -> dict[str, int]:
    """The key-value lines of a cpu.stat (v1 or v2)."""
    stat = {}
    for line in text.splitlines():
        fields = line.split()
        if len(fields) == 2 and fields[1].lstrip("-").isdigit():
            stat[fields[0]] = int(fields[1])
    return stat


def _read(path: Path) -> str | None:
    try:
        return path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError):
        return None


def _quota_at(directory: Path, version: int) -> float | None:
    try:
        if version == 2:
            text = _read(directory / "cpu.max")
            return None if text is None else parse_quota_v2(text)
        quota, period = _read(directory / "cpu.cfs_quota_us"), _read(directory / "cpu.cfs_period_us")
        return None if quota is None or period is None else parse_quota_v1(quota, period)
    except ValueError:
        return None


def _ancestors(directory: Path, top: Path) -> list[Path]:
    """`directory` and each group above it, up to and including the mount's root `top`."""
    chain = [directory]
    while chain[-1] != top and top in chain[-1].parents:
        chain.append(chain[-1].parent)
    return chain


def find_quota(mountinfo: Path = MOUNTINFO, proc_cgroup: Path = PROC_CGROUP) -> QuotaGroup | None:
    """The group whose CPU quota binds this process (the fewest cores), or None: no quota, or no cgroup
    mounted where it can be read."""
    info, own = _read(mountinfo), _read(proc_cgroup)
    if info is None or own is None:
        return None
    mounts, groups = parse_mountinfo(info), parse_proc_cgroup(own)
    best: QuotaGroup | None = None
    for mount in mounts:
        key = "" if mount.version == 2 else ("cpu" if "cpu" in mount.controllers else None)
        if key is None or key not in groups or (directory := group_dir(mount, groups[key])) is None:
            continue
        for level in _ancestors(directory, mount.point):
            cores = _quota_at(level, mount.version)
            if cores is None or (best is not None and cores >= best.cores):
                continue
            usage_dir = level if mount.version == 2 or "cpuacct" in mount.controllers else None
            if usage_dir is None:  # v1 with cpuacct mounted apart: the same group under its mount
                usage_dir = _cpuacct_dir(mounts, groups, directory, level)
            best = QuotaGroup(cores=cores, cpu_dir=level, usage_dir=usage_dir, version=mount.version)
    return best


def _cpuacct_dir(mounts: list[Mount], groups: dict[str, str], own: Path, level: Path) -> Path | None:
    """v1: the cpuacct group as many levels above this process's own as `level` is above `own`."""
    up = len(own.relative_to(level).parts)
    for mount in mounts:
        if mount.version == 1 and "cpuacct" in mount.controllers and "cpuacct" in groups:
            directory = group_dir(mount, groups["cpuacct"])
            if directory is None:
                return None
            chain = _ancestors(directory, mount.point)
            return chain[up] if up < len(chain) else None
    return None


def read_group(group: QuotaGroup) -> GroupCpu | None:
    """Now's reading of the quota group (None: its cpu.stat is gone)."""
    text = _read(group.cpu_dir / "cpu.stat")
    if text is None:
        return None
    stat = parse_cpu_stat(text)
    if group.version == 2:
        usage_us = stat.get("usage_usec")
        usage_ns = None if usage_us is None else 1000 * usage_us
        throttled_ns = 1000 * stat.get("throttled_usec", 0)
    else:
        usage_text = None if group.usage_dir is None else _read(group.usage_dir / "cpuacct.usage")
        usage_ns = int(usage_text) if usage_text is not None and usage_text.strip().isdigit() else None
        throttled_ns = stat.get("throttled_time", 0)
    return GroupCpu(group.cores, usage_ns, throttled_ns)
