"""A witness: one parameter point checked to fit every measured point within its bound (issue 62).

The guaranteed box bounds every parameter that fits from *outside*; it does not say that any
parameter fits at all. Algorithm 3.1 fits each mode to the data minus the other modes' midpoints,
with their worst-case mismatch added to the bound (eq. 3.11, Lemma 3.1): a mode alone can look
consistent while no combination of the modes is (a real plate's file: every mode "verified", the
best fit of the whole model 2.06 bounds off). A witness closes that gap: a point ``x`` of the box with
``max_j |g_j - G(x; j w_j) - r . phi(w_j)| / E_j <= 1``, evaluated on the model itself (no
linearisation), proves the exact feasible set non-empty. When a thorough search finds none, the
identification is not verified and ``identify`` exits 3 naming the best fit's misfit and the points
that bind it.

How it is searched (our choices): local Chebyshev fits
(:func:`~setmem_hil.identification.feasible_points.chebyshev_fit`) from the box's centre, then
from the given hints (the group searches' anchors, a previous iteration's witness), then from
points drawn uniformly in the box (a fixed seed: the same data give the same witness), stopping
at the first that fits. Residual terms (``r_l / s^2``, ``r_u``) enter linearly: for a fixed modal
point their best values are one small second-order cone program (:func:`best_residuals`), and the
fit alternates between the two.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import clarabel
import numpy as np
import scipy.sparse as sp

from setmem_hil.identification.feasible_points import chebyshev_fit, misfit
from setmem_hil.identification.residue_bootstrap import residual_shape
from setmem_hil.model.modal_model import PARAM_NAMES, modal_response

WITNESS_STARTS = 12  # local fits tried at most (the centre, the hints, then uniform draws in the box)
WITNESS_ITERATIONS = 40  # conic steps per local fit at most
RESIDUAL_ROUNDS = 3  # alternations between the modal fit and the residual terms' exact fit
BINDING_SHARE = 0.95  # a point binds the best fit when its misfit is within this share of the worst
BINDING_SHOWN = 6  # binding points named in a message at most


@dataclass(frozen=True)
class Witness:
    """The best point found: ``x`` (``(n_modes, 4)``, the model's column order), the residual terms'
    values, its misfit (``<= 1``: it fits, the set is not empty) and the frequencies of the points
    whose misfit is within ``BINDING_SHARE`` of its worst (those that bind it)."""

    x: np.ndarray
    misfit: float
    residuals: dict = field(default_factory=dict)
    binding_omega_rad_s: tuple[float, ...] = ()
    starts: int = 1

    @property
    def fits(self) -> bool:
        return bool(self.misfit <= 1.0)

    def to_document(self) -> dict:
        """RESULT.json's ``witness`` (public contract, docs/closely-spaced-modes.md)."""
        return {
            "fits": self.fits,
            "misfit": float(self.misfit),
            "modes": [{name: float(row[j]) for j, name in enumerate(PARAM_NAMES)} for row in np.asarray(self.x)],
            "residuals": {name: float(v) for name, v in self.residuals.items()},
            "binding_omega_rad_s": [float(w) for w in self.binding_omega_rad_s],
            "starts": int(self.starts),
        }

    def describe_misfit(self) -> str:
        """One line for a message: the misfit and the points that bind it."""
        shown = ", ".join(f"{w:.6g}" for w in self.binding_omega_rad_s[:BINDING_SHOWN])
        more = f" and {len(self.binding_omega_rad_s) - BINDING_SHOWN} more" if len(self.binding_omega_rad_s) > BINDING_SHOWN else ""
        return f"the best fit found ({self.starts} starts) misses by {self.misfit:.3g} times the bound, binding at omega = {shown}{more} rad/s"


def residual_response(values: dict, omega_rad_s) -> np.ndarray:
    """``sum r phi(w)`` of the residual terms at ``values`` (name -> r)."""
    w = np.asarray(omega_rad_s, dtype=float)
    total = np.zeros(w.shape, dtype=complex)
    for name, r in values.items():
        total = total + r * residual_shape(name, w)
    return total


def best_residuals(omega_rad_s, r, E, bounds: dict) -> dict:
    """The residual terms' values in their bounds that minimise ``max_j |r_j - sum_k r_k phi_k(w_j)| / E_j``
    for the misfit ``r`` left by a modal point: ``min t`` over ``|r_j - Phi_j rho| <= t E_j``, one
    second-order cone per point (Clarabel). The terms are real, so only the real part moves. The
    midpoints where the program fails (a witness is checked on the model anyway)."""
    names = list(bounds)
    mid = {name: 0.5 * (lo + hi) for name, (lo, hi) in bounds.items()}
    w = np.asarray(omega_rad_s, dtype=float)
    E = np.asarray(E, dtype=float)
    use = np.isfinite(E) & (E > 0)
    if not names or not use.any():
        return mid
    w, r, E = w[use], np.asarray(r, dtype=complex)[use], E[use]
    m, n_pts = len(names), w.size
    phi = np.column_stack([residual_shape(name, w) for name in names])
    scale = np.maximum(np.max(np.abs(phi) / E[:, None], axis=0), 1e-300)  # each term in units that move the worst point by ~1
    rows, b = [], []
    for j in range(n_pts):  # [t E_j ; Re r_j - Phi_j rho ; Im r_j] in the second-order cone
        rows += [np.r_[np.zeros(m), -E[j]], np.r_[phi[j] / scale, 0.0], np.zeros(m + 1)]
        b += [0.0, r[j].real, r[j].imag]
    for k, name in enumerate(names):  # lo <= rho_k <= hi, in the scaled units
        lo, hi = bounds[name]
        for sign, limit in ((1.0, hi), (-1.0, -lo)):
            row = np.zeros(m + 1)
            row[k] = sign / scale[k]
            rows.append(row)
            b.append(limit)
    A = sp.csc_matrix(np.array(rows))
    q = np.r_[np.zeros(m), 1.0]
    cones = [clarabel.SecondOrderConeT(3)] * n_pts + [clarabel.NonnegativeConeT(2 * m)]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    solution = clarabel.DefaultSolver(sp.csc_matrix((m + 1, m + 1)), q, A, np.array(b), cones, settings).solve()
    if str(solution.status) not in ("Solved", "AlmostSolved"):
        return mid
    rho = np.asarray(solution.x[:m]) / scale
    return {name: float(np.clip(rho[k], *bounds[name])) for k, name in enumerate(names)}


def total_misfit(x, residuals: dict, omega_rad_s, g, E) -> float:
    """The misfit of a modal point with residual terms (:func:`feasible_points.misfit` of the data
    less the terms)."""
    return misfit(x, omega_rad_s, np.asarray(g, dtype=complex) - residual_response(residuals, omega_rad_s), E)


def _binding(x, residuals: dict, omega_rad_s, g, E, worst: float) -> tuple[float, ...]:
    w = np.asarray(omega_rad_s, dtype=float)
    E = np.asarray(E, dtype=float)
    finite = np.isfinite(E) & (E > 0)
    if not finite.any() or not np.isfinite(worst):
        return ()
    with np.errstate(divide="ignore", invalid="ignore"):
        G = modal_response(np.asarray(x, dtype=float).reshape(-1, 4), w).sum(axis=0) + residual_response(residuals, w)
        ratio = np.abs(np.asarray(g, dtype=complex) - G) / E
    ratio[~finite] = 0.0
    picked = np.flatnonzero(ratio >= BINDING_SHARE * worst)
    return tuple(float(v) for v in w[picked[np.argsort(-ratio[picked])]])


def _local_fit(omega, g, E, lo, hi, start, residual_bounds: dict):
    """One start: the Chebyshev fit, alternating with the residual terms' exact fit."""
    x = np.clip(np.asarray(start, dtype=float).reshape(lo.shape), lo, hi)
    residuals = {name: 0.5 * (a + b) for name, (a, b) in residual_bounds.items()}
    for _ in range(RESIDUAL_ROUNDS if residual_bounds else 1):
        if residual_bounds:
            with np.errstate(divide="ignore", invalid="ignore"):
                left = g - modal_response(x.reshape(-1, 4), omega).sum(axis=0)
            if np.all(np.isfinite(left)):
                residuals = best_residuals(omega, left, E, residual_bounds)
        fitted, _ = chebyshev_fit(omega, g - residual_response(residuals, omega), E, lo, hi, x, iterations=WITNESS_ITERATIONS)
        x = np.asarray(fitted, dtype=float).reshape(lo.shape)
        if total_misfit(x, residuals, omega, g, E) <= 1.0:
            break
    return x, residuals, total_misfit(x, residuals, omega, g, E)


def find_witness(omega_rad_s, g, E, lo, hi, residual_bounds: dict | None = None, hints=(),
                 starts: int = WITNESS_STARTS, seed: int = 0) -> Witness:
    """A point of the box ``[lo, hi]`` (``(n_modes, 4)``) that fits every point, or the best found.

    Local Chebyshev fits from the box's centre, each of ``hints`` inside the box, then uniform
    draws (``seed``), ``starts`` in all, stopping at the first that fits (module docstring). The
    returned :class:`Witness` was evaluated on the model: ``fits`` is a fact, not an estimate;
    ``not fits`` means only that the search found none."""
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    omega = np.asarray(omega_rad_s, dtype=float)
    g = np.asarray(g, dtype=complex)
    E = np.asarray(E, dtype=float)
    residual_bounds = dict(residual_bounds or {})
    rng = np.random.default_rng(seed)
    candidates = [0.5 * (lo + hi)]
    candidates += [np.asarray(h, dtype=float).reshape(lo.shape) for h in hints if h is not None and np.size(h) == lo.size]
    best = None
    tried = 0
    while tried < starts:
        start = candidates[tried] if tried < len(candidates) else lo + rng.random(lo.shape) * (hi - lo)
        tried += 1
        x, residuals, worst = _local_fit(omega, g, E, lo, hi, start, residual_bounds)
        if best is None or worst < best[2]:
            best = (x, residuals, worst)
        if worst <= 1.0:
            break
    x, residuals, worst = best
    return Witness(x=x, misfit=float(worst), residuals=residuals,
                   binding_omega_rad_s=_binding(x, residuals, omega, g, E, worst), starts=tried)
