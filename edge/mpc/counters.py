"""What the MPC service counts, for its health line and its tests."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class MpcCounters:
    states: int = 0
    commands: int = 0
    stale: int = 0
    solve_failures: int = 0
    references: int = 0
    other_shard: int = 0
    not_mine: int = 0  # states of drones this replica neither flies nor stands by for
    copies: int = 0  # a State's later copies by another path, each answered with the same Command
    watch_copies: int = 0  # states copied to the drones' standby (`WATCH_COPY_NS`)
    alerts: int = 0  # times a peer's beats were late enough to take its drones' states in full
    solve_ms: list[float] = field(default_factory=list)

    def solved(self, solve_s: float) -> None:
        """A solve's time, kept for the health line's percentiles (the last 1000 to 2000)."""
        self.solve_ms.append(solve_s * 1000)
        if len(self.solve_ms) > 2000:
            del self.solve_ms[:1000]
