"""Interval bounds of one mode's parameters by conic programming (Problem 3.2) with Clarabel.

Each data point is a 3-dimensional second-order cone ``(C_j, Re(r0_j + J_j x), Im(r0_j + J_j x))``
(eq. 3.26, in the affine form of :mod:`setmem_hil.identification.embedding`); the partition's (or the current)
box on every free parameter is a nonnegative cone. Bounding every free parameter from above and
below is ``2 p`` linear objectives over the same feasible set, so one Clarabel solver is built
per mode with a fixed sparsity pattern and re-solved with ``update(q=...)`` across objectives and
``update(b=...)`` across partitions (the "warm structure" of the issue): only the numbers change.

Guarantee: bounds are padded outward by the solver's tolerance, and when Clarabel stops for a
numerical reason the partition's own box is returned (a valid, if loose, bound).
"""

from __future__ import annotations

from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp

from setmem_hil.identification.embedding import embedding_residual
from setmem_hil.errors import SolverError

_SOLVED = {"Solved", "AlmostSolved"}
_INFEASIBLE = {"PrimalInfeasible", "AlmostPrimalInfeasible"}
PAD_REL = 1e-7
PAD_ABS = 1e-10


@dataclass(frozen=True)
class BoxSolution:
    """Result of bounding every free parameter over one box.

    ``lower``/``upper`` have length 4 (fixed parameters keep their value); ``argmin``/``argmax``
    are the full parameter vectors ``(a1, a0, b1, b0)`` attaining each bound (rows of NaN for
    fixed parameters). ``feasible`` is False when the box holds no consistent parameters.
    """

    feasible: bool
    lower: np.ndarray
    upper: np.ndarray
    argmin: np.ndarray
    argmax: np.ndarray
    n_solves: int
    certificate: np.ndarray | None = None  # per-point dual norms when infeasible


class OneModeProblem:
    """The SOC program of one mode for fixed data, reusable across boxes and objectives.

    Parameters
    ----------
    omega_rad_s, g : arrays
        Data points used (points with infinite error bound must be removed beforehand).
    free : array of bool, shape (4,)
        Which of ``(a1, a0, b1, b0)`` are decision variables; the others are fixed at
        ``fixed_values``.
    """

    def __init__(self, omega_rad_s, g, free, fixed_values):
        self.omega = np.asarray(omega_rad_s, dtype=float)
        self.free = np.asarray(free, dtype=bool)
        self.fixed_values = np.asarray(fixed_values, dtype=float)
        r0, J = embedding_residual(self.omega, g)
        fixed = ~self.free
        r0 = r0 + J[:, fixed] @ self.fixed_values[fixed]
        Jf = J[:, self.free]
        n, p = self.omega.size, int(self.free.sum())
        self.n_points, self.n_free = n, p
        # rows per point: [C ; Re ; Im] with s = b - A x
        A_soc = np.zeros((3 * n, p))
        A_soc[1::3] = -Jf.real
        A_soc[2::3] = -Jf.imag
        self._b_soc = np.zeros(3 * n)
        self._b_soc[1::3] = r0.real
        self._b_soc[2::3] = r0.imag
        A_box = np.vstack([np.eye(p), -np.eye(p)])  # x <= hi ; -x <= -lo
        A = np.vstack([A_soc, A_box])
        self._A = sp.csc_matrix(A)
        self._P = sp.csc_matrix((p, p))
        self._cones = [clarabel.SecondOrderConeT(3) for _ in range(n)] + [clarabel.NonnegativeConeT(2 * p)]
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False  # keep the structure fixed so data updates are allowed
        self._settings = settings
        self._solver = None
        self.n_solves = 0

    def _b(self, C, box_lo, box_hi) -> np.ndarray:
        b_soc = self._b_soc.copy()
        b_soc[0::3] = C
        return np.concatenate([b_soc, box_hi[self.free], -box_lo[self.free]])

    def _solve(self, q, b):
        if self._solver is None:
            self._solver = clarabel.DefaultSolver(self._P, q, self._A, b, self._cones, self._settings)
        else:
            self._solver.update(q=q, b=b)
        self.n_solves += 1
        return self._solver.solve()

    def bound_box(self, C, box_lo, box_hi) -> BoxSolution:
        """Bound every free parameter over ``box_lo <= x <= box_hi`` with per-point bounds ``C``.

        Solves ``min x_p`` and ``max x_p`` for each free ``p`` (Problem 3.2). The first solve
        doubles as the feasibility test: an infeasible box costs one solve.
        """
        box_lo = np.asarray(box_lo, dtype=float)
        box_hi = np.asarray(box_hi, dtype=float)
        b = self._b(np.asarray(C, dtype=float), box_lo, box_hi)
        lower = np.where(self.free, box_lo, self.fixed_values)
        upper = np.where(self.free, box_hi, self.fixed_values)
        argmin = np.full((4, 4), np.nan)
        argmax = np.full((4, 4), np.nan)
        solves_before = self.n_solves
        free_idx = np.flatnonzero(self.free)
        for k, p in enumerate(free_idx):
            for sign in (1.0, -1.0):
                q = np.zeros(self.n_free)
                q[k] = sign
                res = self._solve(q, b)
                status = str(res.status)
                if status in _INFEASIBLE:
                    return BoxSolution(False, lower, upper, argmin, argmax, self.n_solves - solves_before, self._certificate(res))
                if status not in _SOLVED:
                    continue  # numerical trouble: keep the box's own bound (still guaranteed)
                x_full = self.fixed_values.copy()
                x_full[self.free] = np.asarray(res.x)
                value = x_full[p]
                pad = PAD_ABS + PAD_REL * max(abs(value), box_hi[p] - box_lo[p])
                if sign > 0:
                    lower[p] = max(box_lo[p], value - pad)
                    argmin[p] = x_full
                else:
                    upper[p] = min(box_hi[p], value + pad)
                    argmax[p] = x_full
        return BoxSolution(True, lower, upper, argmin, argmax, self.n_solves - solves_before)

    def _certificate(self, res) -> np.ndarray:
        """Norm of each point's cone dual in the infeasibility certificate (Farkas multipliers)."""
        z = np.asarray(res.z, dtype=float)
        if z.size < 3 * self.n_points:
            return np.ones(self.n_points)
        return np.linalg.norm(z[: 3 * self.n_points].reshape(self.n_points, 3), axis=1)

    def is_feasible(self, C, box_lo, box_hi) -> bool:
        """One solve: is any parameter vector in the box consistent with every point?"""
        q = np.zeros(self.n_free)
        q[0] = 1.0
        res = self._solve(q, self._b(np.asarray(C, dtype=float), np.asarray(box_lo, float), np.asarray(box_hi, float)))
        status = str(res.status)
        if status in _INFEASIBLE:
            return False
        if status in _SOLVED:
            return True
        raise SolverError(f"Clarabel stopped with status {status} on a feasibility test of {self.n_points} points")
