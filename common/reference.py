"""A planner Reference placed on the receiver's own clock by its arrival time. Pure.

No clock sync is assumed between planner and receiver: sample 0 is taken as due when the Reference
arrives. The MPC uses it for its horizon; the onboard daemon's fallback uses the last one received to
continue the mission for as long as it covers.

Which reference is newer: the higher planner term first (a replaced planner replica, back after a hang,
is ignored), then, from one replica, the higher seq. Of two replicas on one term (a moment while they
settle who keeps it, edge/replicas.py) the latest to arrive wins: both follow the same mission time.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dynqos.common.messages import Reference

Array = NDArray[np.float64]


def newer(reference: Reference, than: Reference) -> bool:
    if reference.term != than.term:
        return reference.term > than.term
    return reference.replica != than.replica or reference.seq > than.seq


class ReferenceTrack:
    """The latest Reference, placed on the MPC's clock by its arrival time."""

    def __init__(self) -> None:
        self.reference: Reference | None = None
        self.arrival_ns = 0
        self._states = np.zeros((0, 6))
        self._yaw = np.zeros(0)

    def update(self, reference: Reference, arrival_ns: int) -> bool:
        if self.reference is not None and not newer(reference, self.reference):
            return False
        self.reference, self.arrival_ns = reference, arrival_ns
        self._states = np.hstack(
            [np.array(reference.pos_m), np.array(reference.vel_mps)]
        )  # once, not per step
        self._yaw = np.array(reference.yaw_rad)
        return True

    def window(self, start_ns: int, count: int, dt_s: float) -> tuple[Array, Array] | None:
        """States (count, 6) and yaws (count,) from start_ns on, or None with no reference."""
        ref = self.reference
        if ref is None:
            return None
        samples = len(self._states)
        times = (start_ns - self.arrival_ns) / 1e9 + dt_s * np.arange(count)
        index = np.clip(times / ref.dt_s, 0, samples - 1)
        lo = index.astype(int)
        hi = np.minimum(lo + 1, samples - 1)
        frac = (index - lo)[:, None]
        states = self._states[lo] * (1 - frac) + self._states[hi] * frac
        states[times >= ref.dt_s * (samples - 1), 3:] = 0.0  # beyond the last sample: hold it
        return states, self._yaw[np.where(frac[:, 0] < 0.5, lo, hi)]
