"""A drone on more than one path: what each path answers, and which path the camera takes. Pure.

Every State goes out on every path, each copy naming its path, and every edge site answers every copy
it hears (the first solved, a later one with the same Command under its own path). A path's command
RTT is timed from the State's stamp to the first answer to that path's copy, by whichever path it came
down: so it times the path's uplink (where a cell's load is) and the slower path is measured too, not
only the winner. Answers from an edge that does not name the copy's path count for the path they
arrived by. The camera is too heavy to send twice, so it
rides one path: the one with the lowest median RTT over its last `WINDOW` answers among the paths that
answered within the watchdog. It moves only when the other path is `HYSTERESIS` better and the camera
has stayed `DWELL_NS` where it is, so two paths of about equal latency do not toss the camera between
them; when the camera's path stops answering it moves at once (docs/multipath.md).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

from dynqos.common.message_base import MAX_STATUS_SAMPLES
from dynqos.common.stats import SlidingWindow

WINDOW = 25  # answers per path in the median
HYSTERESIS = 0.8  # the other path's median must be below this share of the camera path's
DWELL_NS = 1_000_000_000  # the camera stays at least this long on a path (unless it stops answering)


@dataclass
class PathRecord:
    """One path as the drone sees it."""

    rtts: SlidingWindow = field(default_factory=lambda: SlidingWindow(WINDOW))
    last_heard_ns: int | None = None
    answers: int = 0  # genuine answers heard by this path (first or duplicate)
    wins: int = 0  # of them, applied: the first for their state
    new_rtts: deque[float] = field(
        default_factory=lambda: deque(maxlen=MAX_STATUS_SAMPLES)
    )  # since the last status
    # since the path's own PFSM last stepped (onboard/path_pfsm.py)
    unjudged_rtts: deque[float] = field(default_factory=lambda: deque(maxlen=MAX_STATUS_SAMPLES))
    answered_seq: int = -1  # the newest State this path answered

    def answering(self, now_ns: int, within_ns: int) -> bool:
        return self.last_heard_ns is not None and now_ns - self.last_heard_ns <= within_ns


class Paths:
    """The drone's paths by name, in configured order; the first carries the camera at the start."""

    def __init__(self, names: Sequence[str], watchdog_ns: int, start_ns: int) -> None:
        if not names:
            raise ValueError("a drone has at least one path")
        self.names = tuple(names)
        self.records = {name: PathRecord() for name in self.names}
        self.watchdog_ns = watchdog_ns
        self.camera = self.names[0]
        self.camera_since_ns = start_ns
        self.camera_moves = 0

    def heard(
        self, path: str, rtt_ms: float | None, arrival_ns: int, *, won: bool, state_seq: int = -1
    ) -> None:
        """A genuine answer (accepted, or a duplicate of one) to State `state_seq` arrived by `path`."""
        record = self.records.get(path)
        if record is None:
            return
        record.answers += 1
        record.wins += won
        record.last_heard_ns = arrival_ns
        first = state_seq < 0 or state_seq > record.answered_seq  # the first answer to this copy
        record.answered_seq = max(record.answered_seq, state_seq)
        if first and rtt_ms is not None and rtt_ms >= 0:
            record.rtts.push(rtt_ms)
            record.new_rtts.append(rtt_ms)
            record.unjudged_rtts.append(rtt_ms)

    def answering(self, now_ns: int) -> list[str]:
        """The paths that answered within the watchdog, in configured order."""
        return [n for n in self.names if self.records[n].answering(now_ns, self.watchdog_ns)]

    def median_ms(self, path: str) -> float | None:
        return self.records[path].rtts.percentile(50)

    def camera_path(self, now_ns: int) -> str:
        """Where the camera goes now (and the move, if one is due, is made here)."""
        live = self.answering(now_ns)
        if not live or len(self.names) == 1:
            return self.camera
        best = min(live, key=lambda n: (self.median_ms(n) or float("inf"), self.names.index(n)))
        if best == self.camera:
            return self.camera
        here = self.median_ms(self.camera)
        there = self.median_ms(best)
        lost = self.camera not in live
        better = here is not None and there is not None and there < HYSTERESIS * here
        if lost or (better and now_ns - self.camera_since_ns >= DWELL_NS):
            self.camera, self.camera_since_ns = best, now_ns
            self.camera_moves += 1
        return self.camera

    def take_new_rtts(self) -> tuple[tuple[str, tuple[float, ...]], ...]:
        """Each path's RTTs since the last call (the newest MAX_STATUS_SAMPLES), for the status."""
        out = []
        for name, record in self.records.items():
            out.append((name, tuple(record.new_rtts)))
            record.new_rtts.clear()
        return tuple(out)
