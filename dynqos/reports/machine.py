"""How busy the machine was while a flight was recorded, from the kernel's own CPU accounting: the
figures and the verdict (dynqos/experiment/machine.py takes the samples).

Every process of a flight shares this machine's cores: when they are nearly all busy, a process that
becomes runnable waits for a core, and that wait lands in the latencies the flight measures as if the
network had caused it. So each flight samples the aggregate `cpu` line of /proc/stat every second and
its summary says how busy the machine was (`machine`): the busy share of all cores over the recorded
flight, the largest one-second share, and how many seconds were above `STARVED_SHARE`.

A flight is marked `starved` when more than `STARVED_SECONDS` of its seconds were above 85% busy,
besides those in which its own faults loaded the machine (`own_load_spans`: a process restarted, a
detector flooded from the recorder's session): at
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

The machine is what this process may use. Its cores are those it may run on (its CPU affinity: a
container pinned to some of the host's cores counts only theirs in /proc/stat). And where its control
group has a CPU quota (a container's `--cpus`, a Kubernetes CPU limit; dynqos/experiment/cgroup.py),
that quota is the machine: a second in which the group used more than `STARVED_SHARE` of it counts
as a starved second however idle the host was, and the time the quota held the group's processes is
counted on its own (`throttled_share`, of the flight's time). A flight held for more than
`THROTTLED_SHARE` of it is `throttled`: like a stolen one, its verdict stands, and a test flies it
again when it failed its bounds.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

from dynqos.plan.recording import CpuTimes, Recording

STARVED_SHARE = 0.85
STARVED_SECONDS = 3  # busy seconds beyond those of the flight's own faults
RESTART_TAIL_S = 1.0  # a restarted service still warms up this long after its ready line
# Faults whose load is the harness's by design, for their whole window: the flood's frames are sent
# from the recorder's own session at 100 fps (dynqos/experiment/faults.py), which no drone pays for.
LOADING_FAULTS = ("detector_flood",)
MAX_BUSY_LISTED = 120  # busy seconds listed by when they ended (the count is always whole)
STOLEN_SHARE = 0.10  # the hypervisor's share of the cores over the flight beyond which it is stolen
THROTTLED_SHARE = 0.05  # the share of the flight's time the quota held its group beyond which it is throttled


def busy_share(before: CpuTimes, after: CpuTimes) -> float | None:
    """The share of all cores' time that was busy between two readings (None: no time passed)."""
    total = after.total - before.total
    return None if total <= 0 else max(0.0, min(1.0, (after.busy - before.busy) / total))


def quota_share(before: tuple[float, CpuTimes], after: tuple[float, CpuTimes]) -> float | None:
    """The share of its CPU quota the group used between two (seconds, CpuTimes) readings (None: no
    quota, or its usage unreadable)."""
    a, b = before[1].group, after[1].group
    seconds = after[0] - before[0]
    if a is None or b is None or a.usage_ns is None or b.usage_ns is None or seconds <= 0:
        return None
    return max(0.0, min(1.0, (b.usage_ns - a.usage_ns) / (b.quota_cores * seconds * 1e9)))


def own_load_spans(rec: Recording) -> list[tuple[float, float]]:
    """When the flight's own faults loaded the machine, in seconds into the flight: from each fault's
    (re)start of a process to its ready line and RESTART_TAIL_S after (a service still warms up once
    ready), and the whole of each LOADING_FAULTS window (with the same tail)."""
    if rec.flight_start_ns is None:
        return []
    zero = rec.flight_start_ns
    spans = [
        ((began - zero) / 1e9, (ready - zero) / 1e9 + RESTART_TAIL_S)
        for window in rec.faults
        for began, ready in window.restarts
    ]
    for window in rec.faults:
        if window.fault.kind in LOADING_FAULTS and window.end_ns is not None:
            spans.append(((window.start_ns - zero) / 1e9, (window.end_ns - zero) / 1e9 + RESTART_TAIL_S))
    return spans


def machine_figures(
    samples: list[tuple[float, CpuTimes]], cores: int, own_load: Sequence[tuple[float, float]] = ()
) -> dict[str, Any] | None:
    """What a summary says of the machine, from (seconds into the flight, CpuTimes) taken about every
    second over the recorded flight on `cores` (the flight's `Recording.cores`); None with fewer than
    two samples. A busy second that overlaps `own_load` (`own_load_spans`) is counted apart: the
    flight's own faults loaded the machine then, so it does not make the flight starved."""
    if len(samples) < 2:
        return None
    shares, quota_shares, busy_at, own = [], [], [], 0
    for a, b in itertools.pairwise(samples):
        share, of_quota = busy_share(a[1], b[1]), quota_share(a, b)
        if share is not None:
            shares.append(share)
        if of_quota is not None:
            quota_shares.append(of_quota)
        if max(share or 0.0, of_quota or 0.0) > STARVED_SHARE:
            busy_at.append(round(b[0], 1))
            own += any(lo < b[0] and a[0] < hi for lo, hi in own_load)
    above = len(busy_at)
    first, last = samples[0][1], samples[-1][1]
    whole = busy_share(first, last)
    steal = (last.steal - first.steal) / (last.total - first.total) if last.total > first.total else 0.0
    figures: dict[str, Any] = {
        "cores": cores,
        "busy_share": whole,
        "busy_share_max_1s": max(shares) if shares else None,
        "seconds_above_85": above,
        "seconds_above_85_own_faults": own,  # of those, while the flight's own faults loaded the machine
        "seconds_above_85_at_s": busy_at[:MAX_BUSY_LISTED],  # when each ended, seconds into the flight
        "seconds_sampled": len(shares),
        "steal_share": steal,
        "stolen": steal > STOLEN_SHARE,
        "starved": above - own > STARVED_SECONDS,
    }
    if last.group is not None and first.group is not None:
        seconds = samples[-1][0] - samples[0][0]
        held = (
            (last.group.throttled_ns - first.group.throttled_ns) / (cores * seconds * 1e9)
            if seconds > 0
            else 0
        )
        figures |= {
            "quota_cores": last.group.quota_cores,
            "quota_share": quota_share(samples[0], samples[-1]),
            "quota_share_max_1s": max(quota_shares) if quota_shares else None,
            "throttled_share": held,
            "throttled": held > THROTTLED_SHARE,
        }
    return figures


def recorded_machine(rec: Recording) -> dict[str, Any] | None:
    """`machine_figures` of a flight's recording: its samples, its cores, its own faults' load."""
    return machine_figures(rec.cpu_times, rec.cores, own_load_spans(rec))


def describe(figures: dict[str, Any] | None) -> str:
    """One line for a report."""
    if figures is None:
        return "machine: not measured (no /proc/stat)"
    text = (
        f"machine: {figures['cores']} cores {100 * (figures['busy_share'] or 0):.0f}% busy over the flight "
        f"(largest second {100 * (figures['busy_share_max_1s'] or 0):.0f}%; "
        f"{figures['seconds_above_85']} of {figures['seconds_sampled']} s above 85%"
        + (" of the cores or the quota" if "quota_cores" in figures else "")
        + _own_faults(figures)
    )
    if "steal_share" in figures:  # summaries stored before it was measured have none
        text += f"; {100 * figures['steal_share']:.0f}% taken by the hypervisor"
    if "quota_cores" in figures:
        used = figures["quota_share"]
        text += f"; a CPU quota of {figures['quota_cores']:.2f} cores"
        text += f", {100 * used:.0f}% of it used" if used is not None else ""
        text += f", {100 * figures['throttled_share']:.0f}% of the cores' time held by it"
    text += ")"
    if figures["starved"]:
        text += "; STARVED: the processes waited for cores, so these figures are partly the CPU's"
    if figures.get("stolen"):
        text += "; STOLEN: the host took the cores, so these figures are partly the host's"
    if figures.get("throttled"):
        text += "; THROTTLED: the CPU quota held the processes, so these figures are partly the quota's"
    return text


def judge(ok: bool, failure: str, figures: dict[str, Any] | None) -> tuple[bool, str]:
    """A flight's `ok` and `failure` once the machine is taken into account: a flight that was otherwise
    fine but starved is not ok, and says why and what to do."""
    if ok and figures is not None and figures["starved"]:
        own = figures.get("seconds_above_85_own_faults", 0)
        above, sampled = figures["seconds_above_85"] - own, figures["seconds_sampled"]
        besides = f" besides {own} while its own faults loaded it" if own else ""
        return False, (
            f"starved: the machine{' (or its CPU quota)' if 'quota_cores' in figures else ''} was above "
            f"{100 * STARVED_SHARE:.0f}% busy for {above} of {sampled} s{besides}, so the latencies are "
            "partly the CPU's; fly it again with less running on this machine, or on more cores"
        )
    return ok, failure


def _own_faults(figures: dict[str, Any]) -> str:
    count = figures.get("seconds_above_85_own_faults", 0)  # summaries stored before it was kept: none
    return f", {count} of them while the flight's own faults loaded it" if count else ""
