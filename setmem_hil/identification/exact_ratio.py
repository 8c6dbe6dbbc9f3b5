"""``modes[i].exact_ratio``: each interval over the linearised exact feasible set's extent (issue 47).

The diagnostic RESULT.json and the report give per mode (thesis 3.6 asks the user to check the
split's conservatism): the set linearised at a point of the identified box that fits
(:mod:`setmem_hil.identification.feasible_points`), its extents by linear programs
(:mod:`setmem_hil.identification.exact_set`).
"""

from __future__ import annotations

import numpy as np

from setmem_hil.identification.exact_set import linearised_extent_discs
from setmem_hil.identification.feasible_points import chebyshev_fit, misfit
from setmem_hil.model.modal_model import A0, A1, B0, B1


def exact_ratios(omega_rad_s, g, bound, lower: np.ndarray, upper: np.ndarray, prior_lower: np.ndarray,
                 prior_upper: np.ndarray) -> list[dict | None]:
    """Per mode, each interval's width over the linearised exact set's (``modes[i].exact_ratio`` of
    RESULT.json); ``None`` for every mode when the linearised set is empty, and a parameter is left
    out where the exact set has no width (a fixed parameter).

    Linearised at a point of the box that fits every point (a Chebyshev fit from the box's centre,
    :func:`setmem_hil.identification.feasible_points.chebyshev_fit`), else at the centre (which
    need not fit: a set linearised away from itself). Each extent is a second-order cone program
    over the points' discs (:func:`~setmem_hil.identification.exact_set.linearised_extent_discs`),
    not a polygon's linear program: where the data leave the set thin (a point's disc nearly
    tangent to it, as with noise drawn up to the bound) a 2 % larger disc moves an extent by up to
    25 % (circumscribed 16-gons, used before, read a 1.3x box as 0.97-1.25x on a 10 % pair), and
    64-gons in HiGHS took 15.6 s on the real beam's 384 points. Where the set is large against the
    model's curvature the linearisation itself is off: on a 1 % pair at five times the noise the
    extents of points checked to fit differ from the linearised ones by up to 15 %.
    """
    lower, upper = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    centre = 0.5 * (lower + upper)
    at = centre
    if misfit(centre, omega_rad_s, g, bound) > 1.0:
        fitted, worst = chebyshev_fit(omega_rad_s, g, bound, lower, upper, centre)
        if worst <= 1.0:
            at = fitted.reshape(centre.shape)
    extent = linearised_extent_discs(omega_rad_s, g, bound, at, prior_lower, prior_upper)
    if extent is None:
        return [None] * centre.shape[0]
    ex_lo, ex_hi = extent
    out = []
    for i in range(centre.shape[0]):
        ratios = {}
        for name, col in (("a0", A0), ("a1", A1), ("b0", B0), ("b1", B1)):
            exact = ex_hi[i, col] - ex_lo[i, col]
            if exact > 0 and np.isfinite(exact):
                ratios[name] = float((upper[i, col] - lower[i, col]) / exact)
        out.append(ratios)
    return out
