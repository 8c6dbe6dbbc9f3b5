"""Worst-case mismatch between a mode's midpoint estimate and any mode in its box (Lemma 3.1).

Reducing the multi-mode problem to one-mode problems (eq. 3.11) adds, for every other mode k,
a bound on ``|g_hat_k(j w) - g_k(j w)|`` to the noise bound. With ``g_k = B e^{j psi}``, where
the magnitude ``B`` and phase ``psi`` range over intervals determined by the parameter box,
Lemma 3.1 says the distance from the fixed ``g_hat_k`` is largest at a corner of the
``(B, psi)`` rectangle, unless the phase range (relative to ``g_hat_k``) contains +-pi, in which
case the triangle inequality ``|g_hat_k| + B_max`` is the bound.

Magnitude and phase ranges of ``(b1 s + b0) / (s^2 + a1 s + a0)`` over a box are exact for the
numerator and denominator separately (extremes at box corners or at the point nearest the
origin); treating them as independent is conservative, as the thesis notes.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.identification.embedding import denominator_max, denominator_min
from setmem_hil.model.modal_model import A0, A1, B0, B1, IntervalModel, modal_response


def _interval_abs_range(lo, hi):
    """Min and max of ``|x|`` for ``x`` in ``[lo, hi]`` (elementwise)."""
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    amax = np.maximum(np.abs(lo), np.abs(hi))
    amin = np.where((lo <= 0) & (hi >= 0), 0.0, np.minimum(np.abs(lo), np.abs(hi)))
    return amin, amax


def _box_angle_range(x_lo, x_hi, y_lo, y_hi):
    """Angles of an axis-aligned box in the complex plane, relative to its centre's angle.

    Returns ``(reference, rel_lo, rel_hi, contains_origin)``. A closed box that does not
    contain the origin subtends less than pi, so angles relative to the centre need no wrap.
    """
    contains = (x_lo <= 0) & (x_hi >= 0) & (y_lo <= 0) & (y_hi >= 0)
    ref = np.angle(0.5 * (x_lo + x_hi) + 0.5j * (y_lo + y_hi))
    corners = np.stack([x_lo + 1j * y_lo, x_lo + 1j * y_hi, x_hi + 1j * y_lo, x_hi + 1j * y_hi])
    rel = np.angle(corners * np.exp(-1j * ref))
    return ref, rel.min(axis=0), rel.max(axis=0), contains


def mode_mismatch_bounds(model: IntervalModel, omega_rad_s) -> np.ndarray:
    """``max |g_hat_k(j w) - g_k(j w)|`` over mode k's box, shape ``(n_modes, n_omega)``.

    ``g_hat_k`` is the midpoint model's mode (the thesis's estimate, section 6.2). Entries are
    ``inf`` where the box allows a zero denominator (``a1_lo = 0`` and ``w^2`` in the a0 band)
    or unbounded residues.
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))[None, :]
    lo = model.lower[:, :, None]
    hi = model.upper[:, :, None]
    g_hat = modal_response(model.midpoint.values, w[0])

    # numerator b0 + j b1 w: box x in [b0_lo, b0_hi], y in [b1_lo w, b1_hi w]
    n_x_lo, n_x_hi = lo[:, B0], hi[:, B0]
    n_y_lo, n_y_hi = np.minimum(lo[:, B1] * w, hi[:, B1] * w), np.maximum(lo[:, B1] * w, hi[:, B1] * w)
    b0_min, b0_max = _interval_abs_range(n_x_lo, n_x_hi)
    b1w_min, b1w_max = _interval_abs_range(n_y_lo, n_y_hi)
    num_min, num_max = np.hypot(b0_min, b1w_min), np.hypot(b0_max, b1w_max)

    # denominator (a0 - w^2) + j a1 w: a1 >= 0 keeps it in the closed upper half plane
    a0_lo, a0_hi, a1_lo, a1_hi = lo[:, A0], hi[:, A0], lo[:, A1], hi[:, A1]
    den_min = denominator_min(w, a0_lo, a0_hi, a1_lo)
    den_max = denominator_max(w, a0_lo, a0_hi, a1_hi)

    with np.errstate(divide="ignore", invalid="ignore"):
        mag_lo = np.where(den_max > 0, num_min / den_max, 0.0)
        mag_hi = np.where(den_min > 0, num_max / np.where(den_min > 0, den_min, 1.0), np.inf)
    mag_hi = np.where(np.isfinite(num_max), mag_hi, np.inf)

    n_ref, n_rlo, n_rhi, n_origin = _box_angle_range(n_x_lo, n_x_hi, n_y_lo, n_y_hi)
    d_ref, d_rlo, d_rhi, d_origin = _box_angle_range(a0_lo - w * w, a0_hi - w * w, a1_lo * w, a1_hi * w)

    # phase of g relative to g_hat: psi in [psi_lo, psi_hi]
    ref = n_ref - d_ref - np.angle(g_hat)
    ref = np.angle(np.exp(1j * ref))  # wrap the centre into (-pi, pi]
    psi_lo = ref + n_rlo - d_rhi
    psi_hi = ref + n_rhi - d_rlo
    a = np.abs(g_hat)
    triangle = a + mag_hi
    unknown_phase = n_origin | d_origin | (psi_lo <= -np.pi) | (psi_hi >= np.pi) | (a == 0)
    with np.errstate(invalid="ignore"):
        corners = np.stack(
            [np.abs(a - B * np.exp(1j * psi)) for B in (mag_lo, mag_hi) for psi in (psi_lo, psi_hi)]
        ).max(axis=0)
    bound = np.where(unknown_phase, triangle, corners)
    return np.where(np.isfinite(mag_hi), bound, np.inf)
