"""An affine upper bound of a denominator's magnitude over a box (issue 47, our method).

The thesis's embedding (eq. 3.26) multiplies a point's constraint through by the denominator ``Q``
(``D`` of one mode, ``D_1 D_2`` of a close pair) and over-bounds its magnitude on the right by its
largest value over the box (eq. 3.34):

    |P(x)| <= E |Q(x)| <= E max_box |Q|.

That bound is loose to first order in the box: near a resonance ``|Q|`` varies across the box by as
much as its own size, and every point's disc is inflated by ``max |Q| / |Q(x)|`` (1.5 at the
median, 2.4 at the upper quartile, over the lifted points of a 0.5 % pair's last leaves at five
times the noise). Here ``|Q|`` is over-bounded by an affine function instead, tangent at the box's
centre: with ``u = Q_c / |Q_c|`` and ``Q = Q_c + dQ``, ``|dQ| <= Delta`` over the box,

    |Q| = sqrt(Re(u* Q)^2 + Im(u* Q)^2) <= Re(u* Q) + Im(u* Q)^2 / (2 Re(u* Q))
        <= Re(u* Q) + Delta^2 / (2 (|Q_c| - Delta))         (Delta < |Q_c|),

since ``sqrt(R^2 + I^2) <= R + I^2 / (2 R)`` for ``R > 0``, ``|Im(u* dQ)| <= Delta`` and
``Re(u* Q) >= |Q_c| - Delta``. ``Re(u* Q)`` is affine in whatever ``Q`` is affine in: the
parameters for one mode, the parameters and their products for a pair (its lifted form, where the
products are variables in their McCormick envelopes). ``E`` times it is concave (affine) on the
right of the cone, so the point stays one second-order cone, now ``|P| <= E U(x, z)``, exact to
second order in the box instead of first. It holds at every point of the box with the products
exact, so the relaxed set still holds every fitting parameter.

Where ``Delta`` is not below ``|Q_c|`` (the box spans the point's resonance) or the second-order
term is larger than what the box's maximum gives away at the centre, the maximum is kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_EPS = np.finfo(float).eps


@dataclass(frozen=True)
class AffineMagnitudeBound:
    """``U = constant + slope @ y + product_slope @ z >= |Q|`` per point over the box (``y`` the
    normalised parameters ``x = c + h y``, ``z`` the products); meaningful where ``usable``."""

    constant: np.ndarray  # (N,)
    slope: np.ndarray  # (N, P), per unit of y
    product_slope: np.ndarray  # (N, K), per unit of z
    usable: np.ndarray  # (N,) bool


def affine_magnitude_bound(Q_c, Q_y, Q_z, deviation, box_max) -> AffineMagnitudeBound:
    """The bound of the module docstring for ``Q = Q_c + Q_y @ y + Q_z @ z`` (exact at the box's
    points), ``|Q - Q_c| <= deviation`` over the box, and ``box_max`` the box's ``max |Q|`` (the
    bound it replaces where it is tighter at the centre)."""
    Q_c = np.asarray(Q_c, dtype=complex)
    Q_y = np.asarray(Q_y, dtype=complex).reshape(Q_c.size, -1)
    Q_z = np.asarray(Q_z, dtype=complex).reshape(Q_c.size, -1)
    size = np.abs(Q_c)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(size > 0, np.conj(Q_c) / size, 0.0)
        second = deviation * deviation / (2.0 * (size - deviation))
    # rounding of the formed coefficients and of this sum: a few ulps of every term's size
    rounding = 64 * _EPS * (size + np.sum(np.abs(Q_y), axis=1) + np.sum(np.abs(Q_z), axis=1) + deviation)
    constant = (size + second + rounding) * (1.0 + 1e-12)
    usable = (deviation < size) & np.isfinite(constant) & (constant < box_max)
    return AffineMagnitudeBound(constant, (u[:, None] * Q_y).real, (u[:, None] * Q_z).real, usable)
