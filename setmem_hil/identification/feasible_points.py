"""Points known to fit the data: the exact feasible set bounded from inside (issue 47, our method).

A guaranteed interval bounds every fitting parameter from *outside*. A point checked to fit every
data point within its bound, ``max_j |g_j - G(x; j w_j)| / E_j <= 1``, bounds the exact feasible set
from *inside*: the set reaches at least that far. The hull of such points (the witnesses) tells the
group search (:mod:`setmem_hil.identification.mode_group`) where refining a box can no longer
narrow the answer: a box that sticks out of the witnesses' hull by less than a small fraction of
its width is left as it is, however loose its relaxation, since the interval cannot be narrower
than the hull anyway. Boxes deep inside the set are then never split.

Nothing here is part of the guarantee: a witness only decides where the search spends its boxes.
Every witness is checked by evaluating the model at every point (no linearisation).

How the witnesses are found (our choices):
- the **anchor**: a Chebyshev fit (the smallest largest misfit ``t``), by sequential conic
  programs on the model linearised at the current point, in a trust region that shrinks when a
  step does not lower the true misfit;
- the **extremes**: the group search's own points nearest each bound of a box (its relaxation's
  solutions, which need not fit), pulled back towards the anchor until they fit (bisection). Near
  the set's edge the relaxation is nearly exact, so they fit at or near their full reach.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp

from setmem_hil.identification.exact_set import model_jacobian
from setmem_hil.model.modal_model import modal_response

PULL_BACK_STEPS = 10  # bisection steps along the segment from the anchor to a candidate (to 0.1 %)


def misfit(x, omega_rad_s, g, E) -> float:
    """The largest ``|g_j - G(x; j w_j)| / E_j`` over the points with a finite bound (at most 1: fits)."""
    G = modal_response(np.asarray(x, dtype=float).reshape(-1, 4), omega_rad_s).sum(axis=0)
    E = np.asarray(E, dtype=float)
    finite = np.isfinite(E)
    if not finite.any():
        return 0.0
    return float(np.max(np.abs(np.asarray(g, dtype=complex)[finite] - G[finite]) / E[finite]))


STEP_POINTS = 200  # the worst-fitting points a step's conic program sees (the true misfit judges it)


def _minimax_step(x, omega, g, E, lo, hi, trust):
    """One conic program (Clarabel): ``min t`` over ``|r - J dx| <= t E`` at the ``STEP_POINTS``
    worst-fitting points, ``x + dx`` in the box and ``|dx_p| <= trust * scale_p``. (A polygon in
    place of each disc stalls up to ``1 / cos(pi / sides)`` above the minimum: near 1, that is the
    difference between fitting and not.)"""
    free = hi > lo
    G, J = model_jacobian(x, omega)
    r = g - G
    if r.size > STEP_POINTS:
        worst = np.argsort(np.abs(r) / E)[-STEP_POINTS:]
        r, J, E = r[worst], J[worst], E[worst]
    Jf = J[:, free]
    scale = 1.0 / np.maximum(np.max(np.abs(Jf) / E[:, None], axis=0), 1e-300)
    Jf = Jf * scale[None, :] / E[:, None]
    r = r / E
    n, p = r.size, Jf.shape[1]
    # variables v = (u, t); cones (t, Re(r - J u), Im(r - J u)) as s = b - A v
    A_soc = np.zeros((3 * n, p + 1))
    A_soc[0::3, p] = -1.0
    A_soc[1::3, :p], A_soc[2::3, :p] = Jf.real, Jf.imag
    b_soc = np.zeros(3 * n)
    b_soc[1::3], b_soc[2::3] = r.real, r.imag
    u_hi = np.minimum((hi[free] - x[free]) / scale, trust)
    u_lo = np.maximum((lo[free] - x[free]) / scale, -trust)
    eye = np.hstack([np.eye(p), np.zeros((p, 1))])
    A = sp.csc_matrix(np.vstack([A_soc, eye, -eye]))
    b = np.concatenate([b_soc, u_hi, -u_lo])
    q = np.zeros(p + 1)
    q[p] = 1.0
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    cones = [clarabel.SecondOrderConeT(3) for _ in range(n)] + [clarabel.NonnegativeConeT(2 * p)]
    res = clarabel.DefaultSolver(sp.csc_matrix((p + 1, p + 1)), q, A, b, cones, settings).solve()
    u = np.asarray(res.x, dtype=float)[:p]
    if not np.all(np.isfinite(u)):
        return None
    step = x.copy()
    step[free] = np.clip(x[free] + scale * u, lo[free], hi[free])
    return step


def chebyshev_fit(omega_rad_s, g, E, lo, hi, x0, iterations: int = 15):
    """A local Chebyshev fit inside ``[lo, hi]`` from ``x0`` (module docstring): ``(x, misfit)``.

    Stops early once the misfit is below 0.9 (the point fits with room to spare), or once a step
    gains less than 0.5 %. An anchor well inside the set (not merely fitting) is what lets the
    segments to the candidates stay in it.
    """
    finite = np.isfinite(np.asarray(E, dtype=float))
    omega = np.asarray(omega_rad_s, dtype=float)[finite]
    g = np.asarray(g, dtype=complex)[finite]
    E = np.asarray(E, dtype=float)[finite]
    lo = np.asarray(lo, dtype=float).reshape(-1)
    hi = np.asarray(hi, dtype=float).reshape(-1)
    x = np.clip(np.asarray(x0, dtype=float).reshape(-1), lo, hi)
    f = misfit(x, omega, g, E)
    trust = 4.0
    for _ in range(iterations):
        if f < 0.9 or trust < 1e-3:
            break
        step = _minimax_step(x, omega, g, E, lo, hi, trust)
        if step is None:
            break
        f_step = misfit(step, omega, g, E)
        if f_step < f:
            settled = f_step > 0.995 * f
            x, f = step, f_step
            if settled:
                break
            trust = min(2.0 * trust, 16.0)
        else:
            trust *= 0.25
    return x, f


def pulled_back(candidate, anchor, omega_rad_s, g, E, steps: int = PULL_BACK_STEPS):
    """The furthest point of the segment from ``anchor`` (which fits) towards ``candidate`` found to
    fit, by bisection on the fraction of the way, or ``None`` when none but the anchor does. Every
    point returned was checked (the set need not be convex along the segment: bisection only
    finds *a* far point that fits)."""
    anchor = np.asarray(anchor, dtype=float).reshape(-1)
    direction = np.asarray(candidate, dtype=float).reshape(-1) - anchor
    if misfit(anchor + direction, omega_rad_s, g, E) <= 1.0:
        return anchor + direction
    inside, outside = 0.0, 1.0
    for _ in range(steps):
        t = 0.5 * (inside + outside)
        if misfit(anchor + t * direction, omega_rad_s, g, E) <= 1.0:
            inside = t
        else:
            outside = t
    return None if inside == 0.0 else anchor + inside * direction
