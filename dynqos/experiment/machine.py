"""How busy the machine was while a flight was recorded, from the kernel's own CPU accounting.

Every process of a flight shares this machine's cores: when they are nearly all busy, a process that
becomes runnable waits for a core, and that wait lands in the latencies the flight measures as if the
network had caused it. So each flight samples the aggregate `cpu` line of /proc/stat every second and
its summary says how busy the machine was (`machine`): the busy share of all cores over the recorded
flight, the largest one-second share, and how many seconds were above `STARVED_SHARE`.

A flight is marked `starved` when more than `STARVED_SECONDS` of its seconds were above 85% busy: at
that load a woken process regularly finds every core taken, and on two cores its wait (a scheduler
slice, milliseconds) is a sizeable part of a 16 ms round trip. A few such seconds (start of the load,
a plot) are noise; more say the figures are the CPU's. Steal time (the hypervisor's) counts as busy: the
cores were not ours then. It is also counted on its own (`steal_share`): a host that takes more than
`STOLEN_SHARE` of a virtual machine's cores over a flight has taken them from its latencies too, however
idle the machine looks, since the hypervisor deschedules a virtual core for whole slices at a time and
a 16 ms round trip meets them (seen here: 29% steal over ten seconds in the middle of a CI run whose
flights failed on latency, where the same flights pass at about 2%). Such a flight is `stolen`: its
verdict stands (a flight that held its bounds anyway is a result), but a test flies once more a flight
that failed its bounds while stolen, as it does a starved one (tests/flights.py). A starved flight
is not a result: its summary's `ok` is false and its `failure` says so (`judge`), though every figure
is still written for reading.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STARVED_SHARE = 0.85
STARVED_SECONDS = 3
STOLEN_SHARE = 0.10  # the hypervisor's share of the cores over the flight beyond which it is stolen
PROC_STAT = Path("/proc/stat")


@dataclass(frozen=True, slots=True)
class CpuTimes:
    """All cores' time since boot, in clock ticks: in total, busy (not idle, not waiting on I/O), and
    stolen (the hypervisor ran something else; part of busy)."""

    busy: int
    total: int
    steal: int = 0


def parse_cpu_line(text: str) -> CpuTimes:
    """The aggregate `cpu` line of /proc/stat: user nice system idle iowait irq softirq steal [guest ...];
    guest time is already counted in user and nice, so only the first eight fields add up."""
    for line in text.splitlines():
        fields = line.split()
        if fields and fields[0] == "cpu":
            ticks = [int(v) for v in fields[1:9]]
            ticks += [0] * (8 - len(ticks))
            total = sum(ticks)
            return CpuTimes(busy=total - ticks[3] - ticks[4], total=total, steal=ticks[7])
    raise ValueError("no aggregate cpu line in /proc/stat")


def read_cpu_times(path: Path = PROC_STAT) -> CpuTimes | None:
    """Now's CpuTimes, or None where there is no /proc/stat (the figures are then left out)."""
    try:
        return parse_cpu_line(path.read_text(encoding="ascii"))
    except (OSError, ValueError):
        return None


def busy_share(before: CpuTimes, after: CpuTimes) -> float | None:
    """The share of all cores' time that was busy between two readings (None: no time passed)."""
    total = after.total - before.total
    return None if total <= 0 else max(0.0, min(1.0, (after.busy - before.busy) / total))


def machine_figures(samples: list[tuple[float, CpuTimes]]) -> dict[str, Any] | None:
    """What a summary says of the machine, from (seconds into the flight, CpuTimes) taken about every
    second over the recorded flight; None with fewer than two samples."""
    if len(samples) < 2:
        return None
    pairs = itertools.pairwise(times for _, times in samples)
    shares = [share for a, b in pairs if (share := busy_share(a, b)) is not None]
    first, last = samples[0][1], samples[-1][1]
    whole = busy_share(first, last)
    steal = (last.steal - first.steal) / (last.total - first.total) if last.total > first.total else 0.0
    above = sum(1 for share in shares if share > STARVED_SHARE)
    return {
        "cores": os.cpu_count(),
        "busy_share": whole,
        "busy_share_max_1s": max(shares) if shares else None,
        "seconds_above_85": above,
        "seconds_sampled": len(shares),
        "steal_share": steal,
        "stolen": steal > STOLEN_SHARE,
        "starved": above > STARVED_SECONDS,
    }


def describe(figures: dict[str, Any] | None) -> str:
    """One line for a report."""
    if figures is None:
        return "machine: not measured (no /proc/stat)"
    text = (
        f"machine: {figures['cores']} cores {100 * (figures['busy_share'] or 0):.0f}% busy over the flight "
        f"(largest second {100 * (figures['busy_share_max_1s'] or 0):.0f}%; "
        f"{figures['seconds_above_85']} of {figures['seconds_sampled']} s above 85%"
    )
    if "steal_share" in figures:  # summaries stored before it was measured have none
        text += f"; {100 * figures['steal_share']:.0f}% taken by the hypervisor"
    text += ")"
    if figures["starved"]:
        text += "; STARVED: the processes waited for cores, so these figures are partly the CPU's"
    if figures.get("stolen"):
        text += "; STOLEN: the host took the cores, so these figures are partly the host's"
    return text


def judge(ok: bool, failure: str, figures: dict[str, Any] | None) -> tuple[bool, str]:
    """A flight's `ok` and `failure` once the machine is taken into account: a flight that was otherwise
    fine but starved is not ok, and says why and what to do."""
    if ok and figures is not None and figures["starved"]:
        above, sampled = figures["seconds_above_85"], figures["seconds_sampled"]
        return False, (
            f"starved: the machine was above {100 * STARVED_SHARE:.0f}% busy for {above} of {sampled} s, "
            "so the latencies are partly the CPU's; fly it again with less running on this machine, or on "
            "more cores"
        )
    return ok, failure
