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
- the **farthest**: from the anchor, along every parameter both ways, sequential conic programs
  that maximise the parameter over the model linearised at the current point, each step checked
  on the model and pulled back when it does not fit (:func:`farthest_fitting`). They reach the
  set's extent where a linearisation at one point does not (the set linearised at a 1 % pair's
  truth, at five times the noise, has extremes that miss the data by up to 2.5 bounds);
- the **extremes**: the group search's own points nearest each bound of a box (its relaxation's
  solutions, which need not fit), pulled back towards the anchor until they fit (bisection). Near
  the set's edge the relaxation is nearly exact, so they fit at or near their full reach.

:func:`fitting_extent` gives the extent those points reach, with a nonlinear program's points
besides (:func:`nlp_farthest`, SLSQP): an inner bound of the exact set's, the second reference
of ``benchmarks/close_modes.py``.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp

from setmem_hil.identification.exact_set import model_jacobian
from setmem_hil.model.modal_model import modal_response

PULL_BACK_STEPS = 10  # bisection steps along the segment from the anchor to a candidate (to 0.1 %)


def misfit(x, omega_rad_s, g, E) -> float:
    """The largest ``|g_j - G(x; j w_j)| / E_j`` over the points with a finite bound (at most 1: fits).

    A candidate with an undamped pole exactly at a measured frequency (``a1 = 0``, ``a0 = w_j^2``: a
    box corner where two brackets meet on a measured line) has an infinite response there: it does
    not fit (``inf``), without a division warning reaching the user."""
    with np.errstate(divide="ignore", invalid="ignore"):
        G = modal_response(np.asarray(x, dtype=float).reshape(-1, 4), omega_rad_s).sum(axis=0)
    E = np.asarray(E, dtype=float)
    finite = np.isfinite(E)
    if not finite.any():
        return 0.0
    worst = np.max(np.abs(np.asarray(g, dtype=complex)[finite] - G[finite]) / E[finite])
    return float(worst) if np.isfinite(worst) else float("inf")


STEP_POINTS = 200  # the worst-fitting points a step's conic program sees (the true misfit judges it)


def _unit_steps(J, E) -> np.ndarray:
    """Each parameter's step that alone moves the worst point's misfit ``|J_jp dx| / E_j`` by one:
    the scale of the local searches' variables."""
    return 1.0 / np.maximum(np.max(np.abs(J) / E[:, None], axis=0), 1e-300)


def _minimax_step(x, omega, g, E, lo, hi, trust, toward=None, margin: float = 1.0):
    """One conic program (Clarabel) on the model linearised at ``x``: ``min t`` over ``|r - J dx|
    <= t E`` at the ``STEP_POINTS`` worst-fitting points, ``x + dx`` in the box and ``|dx_p| <=
    trust * scale_p``. With ``toward = (k, sign)`` instead: ``max sign dx_k`` over ``|r - J dx| <=
    margin E`` at those points (a step of :func:`farthest_fitting`; a point left out that the step
    violates is caught by checking the step on the model, and is among the worst at the next). (A polygon in place of each
    disc stalls up to ``1 / cos(pi / sides)`` above the minimum: near 1, that is the difference
    between fitting and not.)"""
    free = hi > lo
    G, J = model_jacobian(x, omega)
    r = g - G
    if r.size > STEP_POINTS:
        worst = np.argsort(np.abs(r) / E)[-STEP_POINTS:]
        r, J, E = r[worst], J[worst], E[worst]
    Jf = J[:, free]
    scale = _unit_steps(Jf, E)
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
    rows, b_lin = [eye, -eye], [u_hi, -u_lo]
    q = np.zeros(p + 1)
    if toward is None:
        q[p] = 1.0
    else:
        k, sign = toward
        q[int(np.sum(free[:k]))] = -sign
        rows.append(np.eye(1, p + 1, p))  # t <= margin
        b_lin.append([margin])
    A = sp.csc_matrix(np.vstack([A_soc] + rows))
    b = np.concatenate([b_soc] + [np.asarray(v, dtype=float) for v in b_lin])
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    cones = [clarabel.SecondOrderConeT(3) for _ in range(n)] + [clarabel.NonnegativeConeT(b.size - 3 * n)]
    res = clarabel.DefaultSolver(sp.csc_matrix((p + 1, p + 1)), q, A, b, cones, settings).solve()
    u = np.asarray(res.x, dtype=float)[:p]
    if not np.all(np.isfinite(u)):
        return None
    step = x.copy()
    step[free] = np.clip(x[free] + scale * u, lo[free], hi[free])
    return step


def _bounded_points(omega_rad_s, g, E, lo, hi):
    """The points with a finite bound (the others constrain nothing) and the box as flat arrays."""
    finite = np.isfinite(np.asarray(E, dtype=float))
    return (np.asarray(omega_rad_s, dtype=float)[finite], np.asarray(g, dtype=complex)[finite],
            np.asarray(E, dtype=float)[finite], np.asarray(lo, dtype=float).reshape(-1),
            np.asarray(hi, dtype=float).reshape(-1))


def chebyshev_fit(omega_rad_s, g, E, lo, hi, x0, iterations: int = 15):
    """A local Chebyshev fit inside ``[lo, hi]`` from ``x0`` (module docstring): ``(x, misfit)``.

    Stops early once the misfit is below 0.9 (the point fits with room to spare), or once a step
    gains less than 0.5 %. An anchor well inside the set (not merely fitting) is what lets the
    segments to the candidates stay in it.
    """
    omega, g, E, lo, hi = _bounded_points(omega_rad_s, g, E, lo, hi)
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


RESTORATION_STEPS = 4  # Chebyshev steps bringing a step that does not fit back onto the set


def _restored(step, k: int, omega, g, E, lo, hi):
    """``step`` brought back to fit with its coordinate ``k`` held: a Chebyshev fit over every other
    free parameter from ``step`` (at most ``RESTORATION_STEPS`` conic programs), or ``None`` when it
    does not reach a misfit of 1. On a curved set a step to the linearised boundary leaves the set by
    a second-order amount; a correction across the boundary keeps the whole gain, where the segment
    back to the last point (bisection) keeps only a fraction of it: without it, the search along a
    close pair's residues stalled at a tenth of the set's extent (1 % pair at five times the noise)."""
    held_lo, held_hi = lo.copy(), hi.copy()
    held_lo[k] = held_hi[k] = step[k]
    x, f_x, trust = step.copy(), misfit(step, omega, g, E), 1.0
    for _ in range(RESTORATION_STEPS):
        trial = _minimax_step(x, omega, g, E, held_lo, held_hi, trust)
        if trial is None:
            return None
        f = misfit(trial, omega, g, E)
        if f <= 1.0:
            return trial
        if f < f_x:
            x, f_x = trial, f
        else:
            trust *= 0.25
    return None


def farthest_fitting(omega_rad_s, g, E, lo, hi, start, k: int, sign: float, iterations: int = 40,
                     restore: bool = False):
    """A point that fits, as far as a local search goes in the direction ``sign`` of parameter
    ``k``, from ``start`` (which fits): sequential conic programs on the model linearised at the
    current point (:func:`_minimax_step` with ``toward``), each step checked on the model itself
    and, when it does not fit, pulled back towards the current point (:func:`pulled_back`); the
    trust region doubles after a step that fits whole and halves after one that did not. Stops
    when a step gains less than 0.1 % of the distance travelled.

    Every point it passes through fits, so its coordinate ``k`` is an *inner* bound on the exact
    feasible set's extent: a reference that needs no linearisation to be exact (the linearised
    set's extremes need not fit where the set is large against the model's curvature: a 1 % pair
    at five times the noise, where they miss by up to 2.5 bounds). A local search: the extent
    found is at most the true one.

    ``restore``: a step that does not fit is first brought back onto the set across the boundary
    (:func:`_restored`), and pulled back along the segment only when that fails. It reaches much
    further on a curved set (a 1 % pair at five times the noise: the lower mode's b1 from 0.10 to
    0.55 of the linearised set's extent, b0 from 0.11 to 0.84) for about four times the conic
    programs. The group search's witnesses do without it: measured on that pair (stop 55), its
    farther witnesses left the answer no narrower (worst ratios 1.60 / 1.76 / 1.98 with it,
    1.64 / 1.66 / 1.83 without) and took 17 % longer; :func:`fitting_extent`, the benchmark's
    inner reference, uses it.
    """
    omega, g, E, lo, hi = _bounded_points(omega_rad_s, g, E, lo, hi)
    x = np.asarray(start, dtype=float).reshape(-1).copy()
    if misfit(x, omega, g, E) > 1.0:
        raise ValueError("farthest_fitting: the start does not fit")
    trust = 1.0
    origin = x[k]
    for _ in range(iterations):
        tol = 1e-3 * abs(x[k] - origin)  # the box's width is no yardstick: it may be the prior's
        step = _minimax_step(x, omega, g, E, lo, hi, trust, toward=(k, sign), margin=1.0 - 1e-9)
        if step is None:
            break
        whole = misfit(step, omega, g, E) <= 1.0
        new = step if whole else (_restored(step, k, omega, g, E, lo, hi) if restore else None)
        if new is None:
            new = pulled_back(step, x, omega, g, E)
        gain = 0.0 if new is None else sign * (new[k] - x[k])
        if gain > 0:
            x = new
        trust = min(2.0 * trust, 64.0) if whole else 0.5 * trust
        if gain < tol and (whole or trust < 1e-3):
            break
    return x


NLP_MARGIN = 1e-6  # SLSQP asked for |r_j|^2 / E_j^2 <= 1 - this: its last iterate may overstep by rounding


def nlp_farthest(omega_rad_s, g, E, lo, hi, start, k: int, sign: float, max_iterations: int = 500):
    """A point that fits, as far as a nonlinear program goes in the direction ``sign`` of parameter
    ``k`` from ``start`` (which fits): ``max sign x_k`` subject to ``|g_j - G(x; j w_j)|^2 <= E_j^2``
    at every point with a finite bound and ``x`` in ``[lo, hi]`` (scipy's SLSQP, the model's exact
    Jacobian; parameters scaled so that each alone moves the worst point's misfit by about one).

    Our choice for the benchmark's inner reference (stop 60): it follows the set's curvature with
    one quasi-Newton model of the constraints, where :func:`farthest_fitting` re-linearises from
    scratch each step and stalls on a curved set. On a 0.5 % pair (opposite residues, the noise of
    issue 47) it reached 1.04-1.40 times the linearised set's extent in about a second for every
    parameter, where :func:`farthest_fitting` (with restoration, six seconds) reached 0.34-1.40.

    Every point returned is checked on the model itself (:func:`misfit`); one that oversteps is
    pulled back towards ``start`` (:func:`pulled_back`). ``None`` when none but ``start`` fits.
    """
    from scipy.optimize import minimize

    omega, g, E, lo, hi = _bounded_points(omega_rad_s, g, E, lo, hi)
    x0 = np.asarray(start, dtype=float).reshape(-1)
    free = np.flatnonzero(hi > lo)
    scale = _unit_steps(model_jacobian(x0, omega)[1][:, free], E)

    def point(z):
        x = x0.copy()
        x[free] = x0[free] + scale * z
        return x

    def room(z):  # >= 0 where the point fits (the response alone: SLSQP asks for it more often than the Jacobian)
        r = (g - modal_response(point(z).reshape(-1, 4), omega).sum(axis=0)) / E
        return (1.0 - NLP_MARGIN) - (r.real ** 2 + r.imag ** 2)

    def room_jacobian(z):
        G, J = model_jacobian(point(z), omega)
        r = (g - G) / E
        dr = -(J[:, free] * scale[None, :]) / E[:, None]
        return -2.0 * (r.real[:, None] * dr.real + r.imag[:, None] * dr.imag)

    c = np.zeros(free.size)
    c[int(np.searchsorted(free, k))] = -sign
    bounds = list(zip((lo[free] - x0[free]) / scale, (hi[free] - x0[free]) / scale))
    with np.errstate(all="ignore"):
        found = minimize(lambda z: c @ z, np.zeros(free.size), jac=lambda z: c, bounds=bounds, method="SLSQP",
                         constraints=[dict(type="ineq", fun=room, jac=room_jacobian)],
                         options=dict(maxiter=max_iterations, ftol=1e-12))
    x = np.clip(point(found.x), lo, hi)
    if not np.all(np.isfinite(x)):
        return None
    return x if misfit(x, omega, g, E) <= 1.0 else pulled_back(x, x0, omega, g, E, steps=30)


def fitting_extent(omega_rad_s, g, E, lo, hi, start, restarts: bool = False):
    """Each parameter's lowest and highest value among points that fit: ``(lower, upper)`` shaped as
    ``lo``, an *inner* bound of the exact feasible set's extent. An interval's width over it is at
    least its width over the exact set: a ratio that can only overstate the method's conservatism
    (fixed parameters: ``lo = hi``, extent 0).

    The points: :func:`nlp_farthest` from ``start`` (a point that fits) along every free parameter
    both ways, and :func:`farthest_fitting` (with restoration) likewise; the farther of the two
    counts. ``restarts``: then :func:`nlp_farthest` again from every point the first pass found,
    along every parameter (a multi-start, the square of the parameters' count in programs: on a
    0.5 % pair at five times the noise it widened the lower mode's a1 from 1.61 to 2.33 times the
    linearised extent, the far mode's b1 from 0.65 to 1.10; about 40 s on 300 lines)."""
    shape = np.shape(lo)
    lo = np.asarray(lo, dtype=float).reshape(-1)
    hi = np.asarray(hi, dtype=float).reshape(-1)
    start = np.asarray(start, dtype=float).reshape(-1)
    lower, upper = start.copy(), start.copy()
    found = []

    def reach(x):
        if x is not None:
            found.append(x)
            np.minimum(lower, x, out=lower)
            np.maximum(upper, x, out=upper)

    searched = np.flatnonzero(hi > lo)
    for k in searched:
        for sign in (-1.0, 1.0):
            reach(nlp_farthest(omega_rad_s, g, E, lo, hi, start, int(k), sign))
            reach(farthest_fitting(omega_rad_s, g, E, lo, hi, start, int(k), sign, restore=True))
    if restarts:
        for x in list(found):
            for k in searched:
                for sign in (-1.0, 1.0):
                    reach(nlp_farthest(omega_rad_s, g, E, lo, hi, x, int(k), sign))
    return lower.reshape(shape), upper.reshape(shape)
