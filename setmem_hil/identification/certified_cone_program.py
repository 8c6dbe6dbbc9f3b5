"""Certified interval bounds over a set of affine second-order cones, Clarabel (Problem 3.2's solver).

The feasible set is ``{x in box : |r_c,j + J_j (x - c)| <= C_j for every point j}``: each point is a
3-dimensional second-order cone ``(C_j, Re, Im)`` of an affine complex residual. The one-mode
problem of the thesis (eq. 3.26, :mod:`setmem_hil.identification.one_mode_solver`) and the
linearised group problem of closely spaced modes (:mod:`setmem_hil.identification.mode_group`)
are both of this form; only the residual's construction differs.

The box on every free parameter is a nonnegative cone. Bounding every free parameter from above and below is ``2 p`` linear
objectives over the same feasible set: one Clarabel solver per pass, re-solved with
``update(q=...)`` across objectives and ``update(b=...)`` across partitions.

Normalisation (issues 12 and 18). The program is posed in the coordinates ``y`` of the pass's
outer box, ``x = c + h y`` with ``c, h`` the box centre and half-width of ``(a1, a0, b1, b0)``:
this is the frequency scaling ``omega -> omega / omega_ref`` (``h_a1 ~ omega_ref``,
``h_a0 ~ omega_ref^2``) and the magnitude scaling of the residues in one step, and each point's
cone is divided by ``sigma_j``, the size of its affine map over the box, which removes the
magnitude of ``g`` and of the bound. Rescaling every frequency by ``S`` and the response by ``m``
therefore leaves the numbers Clarabel sees unchanged up to rounding, and they are O(1) whether
``a0`` is 1 or 4e7 and the receptance 4 or 1e-7 m/N.

Certified bounds (issue 14 item 5; Neumaier and Shcherbina's safe bounds, for conic programs).
A lower bound of ``q^T y`` is never taken from the primal objective. For the solver's dual
vector ``z`` of the point cones, projected into the (self-dual) second-order cone so it is
exactly dual feasible, every feasible ``y`` in the box satisfies

    q^T y >= -b^T z + min_{y in box} (q + A^T z)^T y

(weak duality with the residual ``q + A^T z`` absorbed by the box), which is evaluated with an
outward allowance for floating-point rounding. This bound is valid whatever the solver's status
and accuracy; its distance below the primal objective *is* the tolerance actually reached
(primal and dual residuals and gap), so no fixed padding is used. Likewise a box is declared
empty only when ``z`` satisfies ``b^T z < min_{y in box} (A^T z)^T y`` after the same projection
and rounding allowance (a checked Farkas certificate), or when a certified bound lies beyond the
box (the same weak duality with the objective's term: no point of the box reaches it).

Products of two parameters (issue 47, the lifted form of a close pair). A residual may also be
affine in auxiliary variables ``z_k`` that stand for the product ``y_p y_q`` of two normalised
free parameters. Each ``z_k`` lies in ``[-1, 1]`` and in the product's McCormick envelope over the
box (four linear inequalities ``G v <= h``; exact at the box's corners). The certificates then
carry the envelope's multipliers ``lambda >= 0`` too:

    q^T v >= -b^T z - h^T lambda + min_{v in box} (q + A^T z + G^T lambda)^T v.

Status translation (issue 12 item 6), the rule:

- ``Solved``: its dual gives the certified bound; if that lags the primal objective by more than
  ``CERT_GAP`` of the box width, the objective is re-solved once with tightened tolerances and
  the better certified bound kept.
- ``AlmostSolved`` and every stop for a numerical or iteration reason (``MaxIterations``,
  ``MaxTime``, ``NumericalError``, ``InsufficientProgress``, ``DualInfeasible``...): never a tight
  bound; the certified bound from its dual (usually loose) is used after one tightened re-solve,
  and where no finite certificate exists the box's own bound stands and the bound is flagged
  unverified (still a valid outer bound: the box).
- ``PrimalInfeasible``: the box is dropped only when its certificate checks; otherwise treated as
  feasible with the box's own bounds.
- ``AlmostPrimalInfeasible``: never an infeasibility certificate; re-solved with tightened
  tolerances, and without a checked ``PrimalInfeasible`` the box is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import clarabel
import numpy as np
import scipy.sparse as sp

from setmem_hil.errors import SolverError

SOLVED = "Solved"
PRIMAL_INFEASIBLE = "PrimalInfeasible"
CERT_GAP = 1e-6  # certified bound may lag the objective by this fraction of the box width
_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class ProductTerms:
    """Auxiliary variables of a residual that stand for products of two normalised parameters.

    ``K`` (complex, ``(N, n_aux)``): each point's coefficient of ``z_k``, in the normalised
    coordinates of the program's box (``x = c + h y``, ``z_k = y_p y_q``). ``pairs`` (int,
    ``(n_aux, 2)``): the parameters ``p, q`` (indices into the full parameter vector, both free) of
    each product.
    """

    K: np.ndarray
    pairs: np.ndarray


def mccormick_rows(pairs: np.ndarray, free_index: np.ndarray, n_free: int) -> tuple[np.ndarray, np.ndarray]:
    """The envelope of ``z_k = y_p y_q`` over ``y_p, y_q`` in ``[-1, 1]``, as ``G v <= h`` on
    ``v = (y_free, z)``: ``-z + y_p + y_q <= 1``, ``-z - y_p - y_q <= 1``, ``z - y_p + y_q <= 1``,
    ``z + y_p - y_q <= 1`` (McCormick 1976). ``h`` is widened by a few ulps: the y-box is the x-box
    rounded outward, so its corners may lie an ulp outside ``[-1, 1]``."""
    n_aux = len(pairs)
    G = np.zeros((4 * n_aux, n_free + n_aux))
    for k, (p, q) in enumerate(pairs):
        i, j, col = free_index[p], free_index[q], n_free + k
        for r, (sz, sy) in enumerate(((-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0), (1.0, 1.0))):
            row = 4 * k + r
            G[row, col] = sz
            G[row, i] += sy
            G[row, j] += sy if r < 2 else -sy
    return G, np.full(4 * n_aux, 1.0 + 16 * _EPS)


@dataclass(frozen=True)
class BoxSolution:
    """Result of bounding every free parameter over one box.

    ``lower``/``upper`` have length 4 (fixed parameters keep their value) and are certified
    outer bounds; ``argmin``/``argmax`` are the solver's parameter vectors ``(a1, a0, b1, b0)``
    near each bound (rows of NaN for fixed parameters or uncertified bounds). ``feasible`` is
    False only when the box was proved empty. ``unverified`` names bounds for which no
    certificate was obtained (the box's own bound was kept).
    """

    feasible: bool
    lower: np.ndarray
    upper: np.ndarray
    argmin: np.ndarray
    argmax: np.ndarray
    n_solves: int
    certificate: np.ndarray | None = None  # per-point dual norms when infeasible
    unverified: tuple[str, ...] = field(default_factory=tuple)
    kept: tuple[tuple[int, int], ...] = ()  # the unverified bounds as (parameter, +1 lower / -1 upper)


def _tight_settings(base=None):
    s = clarabel.DefaultSettings()
    s.verbose = False
    s.presolve_enable = False  # keep the structure fixed so data updates are allowed
    if base == "tight":
        s.tol_gap_abs = s.tol_gap_rel = 1e-11
        s.tol_feas = 1e-11
        s.tol_ktratio = 1e-9
        s.max_iter = 400
    return s


class AffineConeProgram:
    """The normalised SOC program ``|r_c + J (x - c)| <= C`` per point, reusable across boxes and
    objectives.

    Parameters
    ----------
    r_c : complex array (N,)
        Each point's residual at the box centre ``c`` (the outer box's midpoint).
    J : complex array (N, P)
        Its derivative with respect to ``x`` (unscaled).
    err_rc : array (N,)
        Absolute rounding error of ``r_c`` as formed (enters the certificates' allowance).
    box_lo, box_hi : arrays (P,)
        The outer box; parameters with ``lo == hi`` are fixed. Every box later given to
        :meth:`bound_box` must lie inside it.
    omega_rad_s : array (N,), optional
        The points' frequencies (kept for diagnostics).
    products : ProductTerms, optional
        Auxiliary product variables of the residuals (module docstring).
    bound_slopes : (array (N, P), array (N, n_aux)), optional
        The radii's slopes per unit of ``x`` and per product: point ``j``'s radius is ``C_j +
        slope_j (x - c) + product_slope_j z`` (an affine bound of a multiplied denominator's
        magnitude, :mod:`setmem_hil.identification.magnitude_bound`), ``C_j`` given to
        :meth:`bound_box`. The certificates need nothing more: the radius is a row of ``A`` like
        the residual's.
    """

    def __init__(self, r_c, J, err_rc, box_lo, box_hi, omega_rad_s=None, products: ProductTerms | None = None,
                 bound_slopes: tuple | None = None):
        box_lo = np.asarray(box_lo, dtype=float)
        box_hi = np.asarray(box_hi, dtype=float)
        self._setup(np.asarray(r_c, dtype=complex), np.asarray(J, dtype=complex), np.asarray(err_rc, dtype=float),
                    box_lo, box_hi, omega_rad_s, products, bound_slopes)

    @staticmethod
    def box_centre(box_lo, box_hi):
        """Centre and half-width used for the normalisation (free unbounded parameters: 0 and 1)."""
        free = box_lo != box_hi
        finite = np.isfinite(box_lo) & np.isfinite(box_hi)
        centre = np.where(finite, 0.5 * (box_lo + box_hi), np.where(free, 0.0, box_lo))
        half = np.where(finite & free, 0.5 * (box_hi - box_lo), 1.0)
        return centre, half

    def _setup(self, r_c, J_unscaled, err_rc_abs, box_lo, box_hi, omega_rad_s, products: ProductTerms | None = None,
               bound_slopes: tuple | None = None):
        n_params = box_lo.size
        self.n_params = n_params
        self.omega = None if omega_rad_s is None else np.asarray(omega_rad_s, dtype=float)
        self.free = box_lo != box_hi
        self.fixed_values = box_lo.copy()
        self.centre, self.half = self.box_centre(box_lo, box_hi)
        J = J_unscaled * self.half[None, :]
        Jf = J[:, self.free]
        n_aux = 0 if products is None else len(products.pairs)
        if n_aux:
            Jf = np.hstack([Jf, np.asarray(products.K, dtype=complex)])
        n, p = r_c.size, int(self.free.sum())
        self.n_points, self.n_free, self.n_aux = n, p, n_aux
        size = np.maximum(np.abs(r_c), np.max(np.abs(Jf), axis=1) if p + n_aux else 0.0)
        positive = size[size > 0]
        floor = positive.min() if positive.size else 1.0
        self.sigma = np.where(size > 0, size, floor)  # per-point cone scaling
        A_soc = np.zeros((3 * n, p + n_aux))
        A_soc[1::3] = -Jf.real / self.sigma[:, None]
        A_soc[2::3] = -Jf.imag / self.sigma[:, None]
        if bound_slopes is not None:
            # the cone's radius affine in the variables (C + slope (x - c) + product_slope z: an
            # affine bound of a denominator's magnitude, magnitude_bound.py); s = b - A v
            slope, product_slope = bound_slopes
            A_soc[0::3, :p] = -(np.asarray(slope, dtype=float) * self.half[None, :])[:, self.free] / self.sigma[:, None]
            if n_aux:
                A_soc[0::3, p:] = -np.asarray(product_slope, dtype=float) / self.sigma[:, None]
        b_soc = np.zeros(3 * n)
        b_soc[1::3] = r_c.real / self.sigma
        b_soc[2::3] = r_c.imag / self.sigma
        self._A_soc, self._b_soc = A_soc, b_soc
        err_rc = err_rc_abs / self.sigma
        self._err_b = np.zeros(3 * n)
        self._err_b[1::3] = err_rc
        self._err_b[2::3] = err_rc
        self._abs_A_soc = np.abs(A_soc)
        free_index = np.cumsum(self.free) - 1
        self._G, self._h = (mccormick_rows(products.pairs, free_index, p) if n_aux
                            else (np.zeros((0, p)), np.zeros(0)))
        nv = p + n_aux
        # s = b - A v: cones, the products' envelopes, v <= hi, -v <= -lo
        A = np.vstack([A_soc, self._G, np.eye(nv), -np.eye(nv)])
        self._A = sp.csc_matrix(A)
        self._P = sp.csc_matrix((nv, nv))
        self._cones = ([clarabel.SecondOrderConeT(3) for _ in range(n)]
                       + [clarabel.NonnegativeConeT(self._h.size + 2 * nv)])
        self._solvers: dict[str, object] = {}
        self.n_solves = 0
        # (parameter index, +1 lower / -1 upper) -> (projected dual z, y-bound) of the last box,
        # kept so tests can re-check every certificate independently
        self.last_certificates: dict[tuple[int, int], tuple[np.ndarray, float]] = {}

    # -- coordinates -----------------------------------------------------------------------
    def _to_y(self, box_lo, box_hi):
        f = self.free
        ylo = (box_lo[f] - self.centre[f]) / self.half[f]
        yhi = (box_hi[f] - self.centre[f]) / self.half[f]
        # outward by one rounding step so the y-box contains the x-box
        return np.nextafter(ylo, -np.inf), np.nextafter(yhi, np.inf)

    def _with_aux(self, ylo, yhi):
        """The box of ``v = (y, z)``: the products lie in ``[-1, 1]`` (widened by an ulp or two)."""
        one = 1.0 + 4 * _EPS
        return (np.concatenate([ylo, np.full(self.n_aux, -one)]), np.concatenate([yhi, np.full(self.n_aux, one)]))

    def _b(self, C, ylo, yhi) -> np.ndarray:
        b_soc = self._b_soc.copy()
        b_soc[0::3] = np.asarray(C, dtype=float) / self.sigma * (1.0 + 4 * _EPS)
        big = 1e20
        vlo, vhi = self._with_aux(ylo, yhi)
        return np.concatenate([b_soc, self._h, np.where(np.isfinite(vhi), vhi, big), np.where(np.isfinite(vlo), -vlo, big)])

    def _solve(self, q, b, mode="default"):
        solver = self._solvers.get(mode)
        if solver is None:
            solver = clarabel.DefaultSolver(self._P, q, self._A, b, self._cones, _tight_settings(mode))
            self._solvers[mode] = solver
        else:
            solver.update(q=q, b=b)
        self.n_solves += 1
        return solver.solve()

    # -- certificates ----------------------------------------------------------------------
    def _dual_soc(self, res) -> np.ndarray | None:
        z = np.asarray(res.z, dtype=float)
        if z.size < 3 * self.n_points or not np.all(np.isfinite(z[: 3 * self.n_points])):
            return None
        z = z[: 3 * self.n_points].reshape(self.n_points, 3).copy()
        norm = np.hypot(z[:, 1], z[:, 2])
        z[:, 0] = np.maximum(z[:, 0], norm * (1.0 + 4 * _EPS))  # exactly inside the dual cone
        return z.reshape(-1)

    def _dual_envelope(self, res) -> np.ndarray:
        """The products' envelope multipliers of ``res``, made exactly nonnegative (empty without
        products)."""
        if not self._h.size:
            return np.zeros(0)
        z = np.asarray(res.z, dtype=float)
        lam = z[3 * self.n_points: 3 * self.n_points + self._h.size] if z.size >= 3 * self.n_points + self._h.size else None
        if lam is None or not np.all(np.isfinite(lam)):
            return np.zeros(self._h.size)
        return np.maximum(lam, 0.0)

    def _round_allowance(self, z, lam, b_soc, q, vlo, vhi):
        """Outward allowance for the rounding in ``b^T z``, ``h^T lambda`` and ``A^T z + G^T lambda``
        (a few ulps per term)."""
        k = (3 * self.n_points + self._h.size + self.n_free + self.n_aux + 4) * _EPS * 2.0
        vmax = np.maximum(np.abs(vlo), np.abs(vhi))
        dual_sizes = self._abs_A_soc.T @ np.abs(z) + np.abs(self._G).T @ lam + np.abs(q)
        return k * (np.abs(b_soc) @ np.abs(z) + self._h @ lam + dual_sizes @ vmax) + self._err_b @ np.abs(z)

    def certified_lower(self, res, q, b, ylo, yhi) -> float:
        """Rigorous lower bound of ``q^T v`` over the feasible set, from the dual of ``res``."""
        z = self._dual_soc(res)
        if z is None:
            return -np.inf
        lam = self._dual_envelope(res)
        vlo, vhi = self._with_aux(ylo, yhi)
        b_soc = b[: 3 * self.n_points]
        r = q + self._A_soc.T @ z + self._G.T @ lam
        box_min = np.sum(np.minimum(r * vlo, r * vhi))
        value = -(b_soc @ z) - self._h @ lam + box_min - self._round_allowance(z, lam, b_soc, q, vlo, vhi)
        return float(value) if np.isfinite(value) else -np.inf

    def certified_empty(self, res, b, ylo, yhi) -> bool:
        """Does ``res.z`` prove that no ``v`` in the box satisfies every point cone (and envelope)?"""
        z = self._dual_soc(res)
        if z is None:
            return False
        lam = self._dual_envelope(res)
        if not (np.any(z) or np.any(lam)):
            return False
        vlo, vhi = self._with_aux(ylo, yhi)
        b_soc = b[: 3 * self.n_points]
        r = self._A_soc.T @ z + self._G.T @ lam
        box_min = np.sum(np.minimum(r * vlo, r * vhi))
        allowance = self._round_allowance(z, lam, b_soc, np.zeros(self.n_free + self.n_aux), vlo, vhi)
        return bool(b_soc @ z + self._h @ lam < box_min - allowance)

    def _certificate(self, res) -> np.ndarray:
        """Norm of each point's cone dual in the infeasibility certificate (Farkas multipliers)."""
        z = np.asarray(res.z, dtype=float)
        if z.size < 3 * self.n_points:
            return np.ones(self.n_points)
        return np.linalg.norm(z[: 3 * self.n_points].reshape(self.n_points, 3), axis=1)

    def _bound_objective(self, q, b, ylo, yhi):
        """Certified lower bound of ``q^T y`` (or None when the box is proved empty).

        Returns ``(bound, y_at, status, result)``; ``bound`` is ``-inf`` when no certificate.
        """
        best, y_at, status, res = -np.inf, None, "", None
        self._best_z = None
        for mode in ("default", "tight"):
            res = self._solve(q, b, mode)
            status = str(res.status)
            if status in ("PrimalInfeasible", "AlmostPrimalInfeasible"):
                if status == PRIMAL_INFEASIBLE and self.certified_empty(res, b, ylo, yhi):
                    return None, None, status, res
                continue  # not a certificate: re-solve tightly, else keep the box
            bound = self.certified_lower(res, q, b, ylo, yhi)
            if bound > best:
                best = bound
                self._best_z = self._dual_soc(res)
                y = np.asarray(res.x, dtype=float)[: self.n_free]
                y_at = y if np.all(np.isfinite(y)) else None
            if status == SOLVED and y_at is not None:
                objective = float(q[: self.n_free] @ y_at)
                if objective - best <= CERT_GAP * float(np.max(yhi - ylo)):
                    break
        return best, y_at, status, res

    def bound_box(self, C, box_lo, box_hi, objectives=None) -> BoxSolution:
        """Certified bounds of every free parameter over ``box_lo <= x <= box_hi`` (Problem 3.2).

        The first solve doubles as the feasibility test: a box proved empty costs one solve.
        ``objectives``: only these ``(parameter, +1 lower / -1 upper)`` bounds are solved, in this
        order (the others keep the box's own bound, a valid outer bound, and are not reported
        unverified); None: every free parameter both ways.
        """
        box_lo = np.asarray(box_lo, dtype=float)
        box_hi = np.asarray(box_hi, dtype=float)
        ylo, yhi = self._to_y(box_lo, box_hi)
        b = self._b(C, ylo, yhi)
        lower = np.where(self.free, box_lo, self.fixed_values)
        upper = np.where(self.free, box_hi, self.fixed_values)
        argmin = np.full((self.n_params, self.n_params), np.nan)
        argmax = np.full((self.n_params, self.n_params), np.nan)
        unverified: list[str] = []
        kept: list[tuple[int, int]] = []
        solves_before = self.n_solves
        self.last_certificates = {}
        free_idx = np.flatnonzero(self.free)
        column = {int(p): k for k, p in enumerate(free_idx)}
        if objectives is None:
            objectives = [(int(p), sign) for p in free_idx for sign in (1.0, -1.0)]
        for p, sign in objectives:
            if int(p) not in column:
                continue  # a fixed parameter: its value is its bound
            k, sign = column[int(p)], float(sign)
            q = np.zeros(self.n_free + self.n_aux)
            q[k] = sign
            bound, y_at, status, res = self._bound_objective(q, b, ylo, yhi)
            if bound is not None and np.isfinite(bound):
                self.last_certificates[(int(p), int(sign))] = (self._best_z, float(bound))
            if bound is None:
                return BoxSolution(False, lower, upper, argmin, argmax, self.n_solves - solves_before,
                                   self._certificate(res))
            if not np.isfinite(bound):
                unverified.append(f"{'lower' if sign > 0 else 'upper'} bound of parameter {p}: solver status {status}, box bound kept")
                kept.append((int(p), int(sign)))
                continue
            x_at = None
            if y_at is not None:
                x_at = self.fixed_values.copy()
                x_at[self.free] = self.centre[self.free] + self.half[self.free] * y_at
            # y-bound -> x-bound, outward by the rounding of centre + half * y
            yb = bound if sign > 0 else -bound
            value = self.centre[p] + self.half[p] * yb
            slack = 4 * _EPS * (abs(self.centre[p]) + abs(self.half[p] * yb))
            if (value - slack > box_hi[p]) if sign > 0 else (value + slack < box_lo[p]):
                # a certified bound beyond the box: weak duality says no point of the box
                # fits (the Farkas test is this with q = 0). Kept as a bound it made the box
                # lie outside itself (a group search's boxes reached 1e143, stop 55).
                return BoxSolution(False, lower, upper, argmin, argmax, self.n_solves - solves_before,
                                   self._certificate(res))
            if sign > 0:
                lower[p] = max(box_lo[p], value - slack)
                if x_at is not None:
                    argmin[p] = x_at
            else:
                upper[p] = min(box_hi[p], value + slack)
                if x_at is not None:
                    argmax[p] = x_at
        return BoxSolution(True, lower, upper, argmin, argmax, self.n_solves - solves_before,
                           unverified=tuple(unverified), kept=tuple(kept))

    def is_feasible(self, C, box_lo, box_hi) -> bool:
        """Is any parameter vector in the box consistent with every point (False only when proved)?"""
        box_lo = np.asarray(box_lo, dtype=float)
        box_hi = np.asarray(box_hi, dtype=float)
        ylo, yhi = self._to_y(box_lo, box_hi)
        b = self._b(C, ylo, yhi)
        q = np.zeros(self.n_free + self.n_aux)
        if self.n_free:
            q[0] = 1.0
        bound, _, status, _ = self._bound_objective(q, b, ylo, yhi)
        if bound is None:
            return False
        if status not in (SOLVED, "AlmostSolved", "PrimalInfeasible", "AlmostPrimalInfeasible") and not np.isfinite(bound):
            raise SolverError(f"Clarabel stopped with status {status} on a feasibility test of {self.n_points} points")
        return True
