"""Residual terms for modes outside the band inside Algorithm 3.1 (issue 14 item 3; our addition).

A lower residual (mass line, ``r_l / s^2``, i.e. ``r_l phi_l`` with ``phi_l = -1/omega^2`` in
receptance) and an upper residual (residual flexibility, ``r_u phi_u`` with ``phi_u = 1``) are
real parameters entering linearly. In Algorithm 3.1 each is one more block beside the modes:

- for the modes, its midpoint estimate is subtracted from the data (like another mode in
  eq. 3.11) and its worst-case mismatch ``|phi(w)| (hi - lo) / 2`` is added to their error bound
  (the analogue of Lemma 3.1, exact for a linear term);
- for the term itself, with every mode's midpoint subtracted and their mismatch added to the
  bound ``E``, each point requires ``|g_r - r phi| <= E``, i.e. ``r phi`` in an interval of the
  real line: ``Re g_r +- sqrt(E^2 - Im(g_r)^2)``. Intersecting over the points gives the exact
  guaranteed interval of ``r`` for the current bounds (no conic program is needed).
"""

from __future__ import annotations

import numpy as np

from setmem_hil.errors import InconsistentDataError
from setmem_hil.identification.residue_bootstrap import residual_shape

_EPS = np.finfo(float).eps


def residual_mismatch(bounds: dict, omega_rad_s, exclude: str | None = None) -> np.ndarray:
    """``sum |phi(w)| (hi - lo) / 2`` over the residual terms (except ``exclude``)."""
    w = np.asarray(omega_rad_s, dtype=float)
    total = np.zeros_like(w)
    for name, (lo, hi) in bounds.items():
        if name != exclude:
            total = total + np.abs(residual_shape(name, w)) * 0.5 * (hi - lo) * (1.0 + 4 * _EPS)
    return total


def residual_midpoint_response(bounds: dict, omega_rad_s, exclude: str | None = None) -> np.ndarray:
    """Receptance of the residual terms at their midpoints (except ``exclude``)."""
    w = np.asarray(omega_rad_s, dtype=float)
    total = np.zeros(w.shape, dtype=complex)
    for name, (lo, hi) in bounds.items():
        if name != exclude:
            total = total + 0.5 * (lo + hi) * residual_shape(name, w)
    return total


def bound_residual(name: str, omega_rad_s, g_r, E, lo: float, hi: float) -> tuple[float, float]:
    """Guaranteed interval of residual ``name`` from ``|g_r - r phi| <= E`` at every point.

    Raises :class:`InconsistentDataError` naming the points when no ``r`` in ``[lo, hi]`` fits.
    """
    w = np.asarray(omega_rad_s, dtype=float)
    g_r = np.asarray(g_r, dtype=complex)
    E = np.asarray(E, dtype=float)
    use = np.isfinite(E)
    phi = residual_shape(name, w)
    new_lo, new_hi = lo, hi
    bad = []
    for wj, gj, ej, pj in zip(w[use], g_r[use], E[use], phi[use]):
        half2 = ej * ej - gj.imag * gj.imag
        slack = 8 * _EPS * (ej * ej + gj.imag * gj.imag)
        if half2 < -slack:
            bad.append(wj)
            continue
        half = np.sqrt(max(half2, 0.0) + slack)
        a, b = (gj.real - half) / pj, (gj.real + half) / pj
        a, b = min(a, b), max(a, b)
        pad = 8 * _EPS * (abs(a) + abs(b))
        new_lo, new_hi = max(new_lo, a - pad), min(new_hi, b + pad)
        if new_lo > new_hi:
            bad.append(wj)
    if bad:
        freqs = ", ".join(f"{v:.6g}" for v in sorted(bad))
        raise InconsistentDataError(
            f"{name} residual: no value within its bounds fits the data points at omega = {freqs} rad/s "
            "within their error bounds (check those measurements and bounds, or widen the prior)",
            omegas_rad_s=sorted(bad), mode_index=None, suspects_rad_s=(),
        )
    return float(new_lo), float(new_hi)
