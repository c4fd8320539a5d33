"""The MPC position controller's QP, set up once in OSQP and updated each step. Pure: no I/O, no clock.

Model: per axis a double integrator with linear drag, x = [p (3), v (3)], u = acceleration (3),
discretised exactly at dt = T_mpc. Cost over the horizon N:
    sum_k (x_k - r_k)' Q (x_k - r_k) + u_k' R u_k  +  (x_N - r_N)' Q_N (x_N - r_N)
subject to the dynamics, |v| <= v_max and a_min <= u <= a_max per axis. The QP is sparse (states and
inputs are both variables, as in OSQP's MPC example): each step only the initial state (l, u) and the
reference (q) change, and the previous solution warm-starts the next.
"""

from __future__ import annotations

import math

import numpy as np
import osqp
import scipy.sparse as sp
from numpy.typing import NDArray

from dynqos.common.config import ControlConfig, MpcConfig

Array = NDArray[np.float64]
NX, NU = 6, 3


def discretise(dt: float, drag: float) -> tuple[Array, Array]:
    """Exact zero-order-hold discretisation of p' = v, v' = u - drag v, per axis."""
    if drag > 1e-9:
        e = math.exp(-drag * dt)
        a_pv, a_vv = (1 - e) / drag, e
        b_p, b_v = (dt - (1 - e) / drag) / drag, (1 - e) / drag
    else:
        a_pv, a_vv, b_p, b_v = dt, 1.0, 0.5 * dt * dt, dt
    eye = np.eye(3)
    ad = np.block([[eye, a_pv * eye], [np.zeros((3, 3)), a_vv * eye]])
    bd = np.vstack([b_p * eye, b_v * eye])
    return ad, bd


class SolveError(RuntimeError):
    """OSQP did not converge to a solution; the caller sends nothing (the drone's watchdog acts)."""


class MpcProblem:
    """The weights and limits are `[mpc]`; the step and horizon are `[control]` (the drone's T_mpc)."""

    def __init__(self, mpc: MpcConfig | None = None, control: ControlConfig | None = None) -> None:
        s = self.mpc = mpc or MpcConfig()
        timing = control or ControlConfig()
        self.dt_s = dt_s = timing.t_mpc_s
        self.horizon = n = timing.horizon
        self.ad, self.bd = discretise(dt_s, s.drag_per_s)
        q = np.diag([s.q_pos] * 3 + [s.q_vel] * 3)
        self._q = q
        self._qn = q * s.terminal_factor
        r = s.r_acc * np.eye(NU)
        p = sp.block_diag([sp.kron(sp.eye(n), q), self._qn, sp.kron(sp.eye(n), r)], format="csc")
        ax = sp.kron(sp.eye(n + 1), -sp.eye(NX)) + sp.kron(sp.eye(n + 1, k=-1), self.ad)
        bu = sp.kron(sp.vstack([sp.csc_matrix((1, n)), sp.eye(n)]), self.bd)
        a_eq = sp.hstack([ax, bu])
        self.n_var = (n + 1) * NX + n * NU
        a_ineq = sp.eye(self.n_var)
        x_min = np.array([-np.inf] * 3 + [-v for v in s.v_max_mps])
        x_max = -x_min
        u_max = np.array(s.a_max_mps2)
        self._l_ineq = np.concatenate([np.tile(x_min, n + 1), np.tile(-u_max, n)])
        self._u_ineq = np.concatenate([np.tile(x_max, n + 1), np.tile(u_max, n)])
        self.a = sp.vstack([a_eq, a_ineq], format="csc")
        self.p = p
        self._l = np.concatenate([np.zeros((n + 1) * NX), self._l_ineq])
        self._u = np.concatenate([np.zeros((n + 1) * NX), self._u_ineq])
        self._qvec = np.zeros(self.n_var)
        self._a_max = np.array(s.a_max_mps2)
        # Velocity bounds as a funnel: a drone that is already faster than v_max (after a gust, or when
        # control returns from the fallback) must be allowed to brake, or the QP is infeasible and no
        # command goes out. Bound at step k: max(v_max, |v0| - 0.9 a_max k dt), per axis.
        self._v_max = np.array(s.v_max_mps)
        self._braking = 0.9 * self._a_max * dt_s * np.arange(n + 1)[:, None]
        rows = (n + 1) * NX + np.arange(n + 1)[:, None] * NX + 3 + np.arange(3)[None, :]
        self._v_rows = rows.ravel()
        infinity = osqp.constant("OSQP_INFTY")  # OSQP's own infinity: what its update() clamps to
        self._l, self._u = np.maximum(self._l, -infinity), np.minimum(self._u, infinity)
        self.solver = osqp.OSQP()
        self.solver.setup(
            p,
            self._qvec,
            self.a,
            self._l,
            self._u,
            warm_starting=True,
            verbose=False,
            polishing=False,
            eps_abs=s.eps,
            eps_rel=s.eps,
            max_iter=s.max_iter,
        )
        # The compiled solver under osqp's Python class. Its update() and solve() wrap these two calls in
        # a module lookup, two clamps, a derivative cache and a namespace of every info field: a quarter
        # of the MPC's time per command at 100 drones (docs/benchmarks.md). The bounds are clamped once
        # above, and nothing here takes derivatives.
        self._ext = self.solver._solver
        self.last_solve_s = 0.0
        self.last_iterations = 0

    def vectors(self, x0: Array, reference: Array) -> tuple[Array, Array, Array]:
        """(q, l, u) for initial state x0 (6) and reference states (N + 1, 6)."""
        n = self.horizon
        if reference.shape != (n + 1, NX):
            raise ValueError(f"reference must have shape {(n + 1, NX)}, got {reference.shape}")
        q = self._qvec
        q[: n * NX] = -(reference[:n] @ self._q).ravel()  # Q symmetric: -Q r_k for each k
        q[n * NX : (n + 1) * NX] = -(self._qn @ reference[n])
        self._l[:NX] = -x0
        self._u[:NX] = -x0
        bound = self.velocity_bounds(x0[3:]).ravel()
        self._u[self._v_rows] = bound
        self._l[self._v_rows] = -bound
        return q, self._l, self._u

    def velocity_bounds(self, v0: Array) -> Array:
        """The funnel's bound on |v| at steps 0..N for initial velocities v0: (3,) gives (N + 1, 3), and
        a batch (B, 3) gives (B, N + 1, 3)."""
        bounds: Array = np.maximum(np.abs(v0)[..., None, :] - self._braking, self._v_max)
        return bounds

    def solve(self, x0: Array, reference: Array) -> Array:
        """The optimal inputs (N, 3); raises SolveError when OSQP does not solve the problem."""
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(reference))):
            raise SolveError("non-finite initial state or reference")
        q, lower, upper = self.vectors(x0, reference)
        self._ext.update_data_vec(q=q, l=lower, u=upper)
        self._ext.solve()
        info = self._ext.info
        self.last_solve_s = float(info.solve_time)
        self.last_iterations = int(info.iter)
        if info.status_val != osqp.SolverStatus.OSQP_SOLVED:
            raise SolveError(f"OSQP status {info.status}")
        n = self.horizon
        inputs: Array = self._ext.solution.x[(n + 1) * NX :].reshape(n, NU)
        return np.clip(inputs, -self._a_max, self._a_max)

    def predict(self, x0: Array, inputs: Array) -> Array:
        """States after applying `inputs` (k, 3) from x0: shape (k + 1, 6)."""
        states = [np.asarray(x0, float)]
        for u in inputs:
            states.append(self.ad @ states[-1] + self.bd @ u)
        return np.array(states)
