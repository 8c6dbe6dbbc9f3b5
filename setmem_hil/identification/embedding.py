"""Convex embedding of the one-mode set-membership problem (thesis section 3.2.2-3.2.3).

For one mode and a data point ``g = g(j omega)`` with error bound ``E``, eq. (3.25)
``|g - (b1 j w + b0) / (-w^2 + a1 j w + a0)| <= E`` is multiplied through by the denominator
and its right-hand side over-bounded over the box of ``(a0, a1)`` (eq. 3.26)::

    |g (-w^2 + a1 j w + a0) - (b1 j w + b0)| <= C(w) = max_{a0 in {lo, hi}} |-w^2 + a1_hi j w + a0| E

The left side is affine in ``x = (a1, a0, b1, b0)``: ``|r0 + J x|`` with ``r0 = -w^2 g`` and
``J = [j w g, g, -j w, -1]``; squared, it is the ellipsoid ``x^T Q x <= C^2`` of eq. (3.27).
Each point is therefore a second-order cone constraint of dimension 3.

The conservatism of the embedding at a point is the ratio of eq. (3.29); the box-wide bound
uses the min/max of ``|-w^2 + a1 j w + a0|`` over the box (eq. 3.34-3.35).
"""

from __future__ import annotations

import numpy as np


def embedding_residual(omega_rad_s, g) -> tuple[np.ndarray, np.ndarray]:
    """Affine form ``r0 + J x`` of the left side of eq. (3.26), ``x = (a1, a0, b1, b0)``.

    Returns ``r0`` (complex, shape ``(N,)``) and ``J`` (complex, shape ``(N, 4)``).
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    g = np.atleast_1d(np.asarray(g, dtype=complex))
    jw = 1j * w
    r0 = -(w**2) * g
    J = np.stack([jw * g, g, -jw, -np.ones_like(jw)], axis=-1)
    return r0, J


def denominator_max(omega_rad_s, a0_lo, a0_hi, a1_hi) -> np.ndarray:
    """``max |-w^2 + a1 j w + a0|`` over ``a0 in [lo, hi]``, ``a1 in [0, a1_hi]`` (eq. 3.34)."""
    w = np.asarray(omega_rad_s, dtype=float)
    w2 = w * w
    real = np.maximum(np.abs(a0_lo - w2), np.abs(a0_hi - w2))
    return np.hypot(real, a1_hi * w)


def denominator_min(omega_rad_s, a0_lo, a0_hi, a1_lo) -> np.ndarray:
    """``min |-w^2 + a1 j w + a0|`` over the box (eq. 3.35)."""
    w = np.asarray(omega_rad_s, dtype=float)
    w2 = w * w
    real = np.clip(w2, a0_lo, a0_hi) - w2
    return np.hypot(real, a1_lo * w)


def embedding_bound(omega_rad_s, E, a0_lo, a0_hi, a1_hi) -> np.ndarray:
    """``C(w)`` of eq. (3.26): the over-bounded right-hand side of one point's constraint."""
    E = np.asarray(E, dtype=float)
    with np.errstate(invalid="ignore"):
        C = denominator_max(omega_rad_s, a0_lo, a0_hi, a1_hi) * E
    return np.where(np.isinf(E), np.inf, C)


def conservatism_ratio(omega_rad_s, a0_lo, a0_hi, a1_lo, a1_hi) -> float:
    """Upper bound on the embedding's ratio of conservatism gamma (eq. 3.29) at the given points.

    The thesis's gamma uses a candidate's own ``(a0, a1)`` in the denominator; taking the minimum
    over the whole box (eq. 3.35) bounds it from above for every candidate in the box.
    Returns ``inf`` when a point can see a zero denominator (``a1_lo = 0`` inside the a0 band).
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    if w.size == 0:
        return 1.0
    num = denominator_max(w, a0_lo, a0_hi, a1_hi)
    den = denominator_min(w, a0_lo, a0_hi, a1_lo)
    with np.errstate(divide="ignore"):
        ratio = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)
    return float(np.max(ratio))


def redundant_points(omega_rad_s, g, E, lo, hi) -> np.ndarray:
    """Points whose constraint holds for every parameter in the box ``[lo, hi]`` (our addition).

    Over the box, ``|r0 + J x| <= |r0 + J c| + sum_p |J_p| h_p`` (centre ``c``, half-width ``h``).
    When this is at most ``min |D| E`` (eq. 3.35 times the bound), the point's constraint in the
    embedding (eq. 3.26), in every sub-box of a partition, and in the exact set (eq. 3.25) is
    inactive: dropping it changes no bound and no conservatism ratio. Far from a mode's band the
    other modes' mismatch makes most points so, and the conic programs shrink accordingly.
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    E = np.asarray(E, dtype=float)
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return np.zeros(w.shape, dtype=bool)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    g = np.atleast_1d(np.asarray(g, dtype=complex))
    jw = 1j * w
    r_c = g * ((c[1] - w * w) + jw * c[0]) - (jw * c[2] + c[3])
    spread = np.abs(g) * (w * h[0] + h[1]) + w * h[2] + h[3]
    worst = np.abs(r_c) + spread
    with np.errstate(invalid="ignore"):  # an infinite bound at a zero denominator: NaN, never redundant
        floor = denominator_min(w, lo[1], hi[1], lo[0]) * E
    # a relative margin far above rounding keeps the test safe in floating point
    return np.isfinite(E) & (worst * (1.0 + 1e-9) + 1e-300 < floor * (1.0 - 1e-9))
