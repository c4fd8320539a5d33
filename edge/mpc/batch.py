"""The fleet's MPC problems solved together. Pure: no I/O, no clock.

Every drone a process serves has the same QP (edge/mpc/problem.py): the same model, weights, limits and
horizon; only the initial state and the reference differ. Without its bounds (the dynamics kept), the
QP's optimum is linear in those two, u* = K [x0; r], so one matrix product gives it for the whole batch.
Where that optimum satisfies every bound (each input within a_max, each velocity within its funnel),
it is the bounded QP's exact optimum too: the KKT conditions hold with zero multipliers. Only the drones
whose bounds bind are left to OSQP, each warm-started on its own problem, as one by one. A hovering or
cruising fleet binds rarely; a climb, a gust or a return from the fallback does, and is solved exactly
as before (`BatchCounters` says how often, in the MPC's health line).

The unbounded optimum is OSQP's answer without OSQP's tolerance: the two differ by what `[mpc] eps`
allows (docs/edge.md, "Batched solves", states it and tests/test_mpc_batch.py holds it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dynqos.edge.mpc.problem import NU, NX, Array, MpcProblem, SolveError


@dataclass
class BatchCounters:
    batches: int = 0
    exact: int = 0  # no bound binds: the unbounded optimum is the answer
    iterative: int = 0  # a bound binds: OSQP solved it
    largest: int = 0  # the most drones in one batch


class UnboundedOptimum:
    """u* = K [x0; r] for the QP's template (any of the fleet's problems: they share their matrices),
    with the state trajectory it leads to, to check the velocity bounds."""

    def __init__(self, problem: MpcProblem) -> None:
        n = problem.horizon
        a, b = problem.ad, problem.bd
        powers = [np.eye(NX)]
        for _ in range(n):
            powers.append(a @ powers[-1])
        s_x = np.vstack(powers)  # x_k = A^k x0 + sum_j A^(k-1-j) B u_j
        s_u = np.zeros(((n + 1) * NX, n * NU))
        for k in range(1, n + 1):
            for j in range(k):
                s_u[k * NX : (k + 1) * NX, j * NU : (j + 1) * NU] = powers[k - 1 - j] @ b
        q_bar = np.kron(np.eye(n + 1), problem._q)
        q_bar[n * NX :, n * NX :] = problem._qn
        hessian = s_u.T @ q_bar @ s_u + problem.mpc.r_acc * np.eye(n * NU)
        k_x = -np.linalg.solve(hessian, s_u.T @ q_bar @ s_x)
        k_r = np.linalg.solve(hessian, s_u.T @ q_bar)
        self.gain = np.hstack([k_x, k_r]).T  # rows [x0; r]: inputs = [x0, r] @ gain
        # the velocities of x_1..x_N (x_0's is the initial state's own, inside its funnel by construction)
        rows = (np.arange(1, n + 1)[:, None] * NX + 3 + np.arange(3)[None, :]).ravel()
        self.vel_from_x0 = s_x[rows].T
        self.vel_from_u = s_u[rows].T
        self.horizon = n
        self.a_max = problem._a_max
        self.velocity_bounds = problem.velocity_bounds  # the same funnel as the QP's own

    def solve(self, x0: Array, reference: Array) -> tuple[Array, NDArray[np.bool_]]:
        """For B drones, x0 (B, 6) and reference (B, N + 1, 6): the inputs (B, N, 3) and, per drone,
        whether no bound binds (B,)."""
        batch = x0.shape[0]
        inputs = np.hstack([x0, reference.reshape(batch, -1)]) @ self.gain
        vel = (x0 @ self.vel_from_x0 + inputs @ self.vel_from_u).reshape(batch, self.horizon, 3)
        funnel = self.velocity_bounds(x0[:, 3:])[:, 1:]
        inside = np.all(np.abs(inputs).reshape(batch, self.horizon, NU) <= self.a_max, axis=(1, 2))
        inside &= np.all(np.abs(vel) <= funnel, axis=(1, 2))
        return inputs.reshape(batch, self.horizon, NU), inside


class BatchSolver:
    """Solves many drones' problems in one call: the unbounded optimum for all, OSQP where a bound binds."""

    def __init__(self, batched: bool = True) -> None:
        self.batched = batched  # False: OSQP for every drone, one by one (`[mpc] batch_solves = false`)
        self._optimum: UnboundedOptimum | None = None
        self.counters = BatchCounters()
        self.product_s: float | None = None  # how long the last batch's product took (None: no product)

    def solve(
        self, problems: list[MpcProblem], x0: list[Array], references: list[Array]
    ) -> list[Array | SolveError]:
        """The optimal inputs (N, 3) per problem, or the SolveError its OSQP solve raised."""
        if not problems:
            return []
        count = len(problems)
        c = self.counters
        c.batches += 1
        c.largest = max(c.largest, count)
        inside = np.zeros(count, dtype=bool)
        exact: Array = np.empty(0)
        share, self.product_s = 0.0, None
        if self.batched:
            if self._optimum is None:
                self._optimum = UnboundedOptimum(problems[0])
            started = time.perf_counter()
            starts, refs = np.array(x0), np.array(references)
            finite = np.isfinite(starts).all(axis=1) & np.isfinite(refs).all(axis=(1, 2))
            exact, within = self._optimum.solve(starts, refs)
            inside = within & finite  # a non-finite one goes to OSQP's path, which refuses it
            self.product_s = time.perf_counter() - started
            share = self.product_s / count
        results: list[Array | SolveError] = []
        for i, problem in enumerate(problems):
            if inside[i]:
                c.exact += 1
                problem.last_solve_s, problem.last_iterations = share, 0
                results.append(exact[i])
                continue
            c.iterative += 1
            try:
                results.append(problem.solve(x0[i], references[i]))  # raises on non-finite too
            except SolveError as exc:
                results.append(exc)
        return results
