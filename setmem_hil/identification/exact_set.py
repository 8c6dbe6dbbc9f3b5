"""The exact feasible set's extent, linearised: the reference a guaranteed interval is held against.

The exact feasible set is every parameter vector, inside the prior, that fits every point within
its bound: ``|g_j - G(x; j w_j)| <= R_j``. It is not convex, but where the data determine the
modes it is tiny, and the model linearised at a point ``x*`` of it,
``G(x) ~ G(x*) + J (x - x*)``, describes it to many digits. Each parameter's extent over the
linearised set is then a linear program: every point's disc ``|r_j - J_j dx| <= R_j`` is replaced by
the inscribed regular polygon of ``sides`` sides (so the reference is never wider than the disc's
set; ``cos(pi / sides)`` of it at worst), and HiGHS (scipy) finds the extremes.

This is independent of the identification's conic programs (another solver, another relaxation)
and is what ``modes[i].exact_ratio`` in RESULT.json and ``benchmarks/close_modes.py`` compare
against (issue 47). Thesis section 3.6 asks the user to check the conservatism of the split; this
is the check.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.optimize import linprog

from setmem_hil.model.modal_model import A0, A1, B0, B1


def model_jacobian(values: np.ndarray, omega_rad_s) -> tuple[np.ndarray, np.ndarray]:
    """``G(x; j w)`` and its derivative with respect to every ``(a1, a0, b1, b0)`` of every mode.

    Returns ``(G (N,), J (N, 4 n))``, parameters in the model's row-major order.
    """
    p = np.asarray(values, dtype=float).reshape(-1, 4)
    w = np.asarray(omega_rad_s, dtype=float)
    s = 1j * w
    J = np.zeros((w.size, p.size), dtype=complex)
    G = np.zeros(w.size, dtype=complex)
    for i, (a1, a0, b1, b0) in enumerate(p):
        D = s * s + a1 * s + a0
        N = b1 * s + b0
        G += N / D
        J[:, 4 * i + A1] = -N * s / D**2
        J[:, 4 * i + A0] = -N / D**2
        J[:, 4 * i + B1] = s / D
        J[:, 4 * i + B0] = 1.0 / D
    return G, J


def _linearised_program(omega_rad_s, g, bound, at, lower, upper, sides: int, inscribed: bool):
    """The linear program of the linearised set (module docstring): ``(A, b, bounds, free, scale,
    x0)`` in the unknowns ``dx / scale`` of the free parameters."""
    x0 = np.asarray(at, dtype=float).reshape(-1)
    n_par = x0.size
    lower = np.full(n_par, -np.inf) if lower is None else np.asarray(lower, dtype=float).reshape(-1)
    upper = np.full(n_par, np.inf) if upper is None else np.asarray(upper, dtype=float).reshape(-1)
    free = upper > lower
    G, J = model_jacobian(x0, omega_rad_s)
    r = np.asarray(g, dtype=complex) - G
    R = np.asarray(bound, dtype=float)
    keep = np.isfinite(R)
    r, Jf, R = r[keep], J[keep][:, free], R[keep]
    # unknowns dx / scale with a unit step moving the worst point by one bound: a well-scaled LP
    # whatever the parameters' magnitudes (b1 = 0 beside a0 = 1e6)
    scale = 1.0 / np.maximum(np.max(np.abs(Jf) / R[:, None], axis=0), 1e-300)
    Jf = Jf * scale[None, :]
    phis = np.pi * 2 * np.arange(sides) / sides
    rot = np.exp(-1j * phis)
    # Re(e^{-j phi} (r - J dx)) <= R cos(pi / sides)  <=>  -Re(e^{-j phi} J) dx <= R cos - Re(e^{-j phi} r)
    A = -(rot[:, None, None] * Jf[None, :, :]).real.reshape(-1, Jf.shape[1])
    radius = R * (np.cos(np.pi / sides) if inscribed else 1.0)
    b = (radius[None, :] - (rot[:, None] * r[None, :]).real).reshape(-1)
    norm = np.maximum(np.abs(A).max(axis=1), 1e-300)
    A, b = A / norm[:, None], b / norm
    bounds = [((lo - x) / s if np.isfinite(lo) else None, (hi - x) / s if np.isfinite(hi) else None)
              for lo, hi, x, s in zip(lower[free], upper[free], x0[free], scale)]
    return A, b, bounds, free, scale, x0


def linearised_extremes(omega_rad_s, g, bound, at: np.ndarray, lower: np.ndarray | None = None,
                        upper: np.ndarray | None = None, sides: int = 64, inscribed: bool = True):
    """Each free parameter's lowest and highest point of the feasible set linearised at ``at``.

    Returns a list of ``(index, sign, x)``: the parameter's flat index, ``+1`` for its lowest point
    and ``-1`` for its highest, and the whole parameter vector there (flat; ``None`` where the
    program was unbounded); ``None`` instead of the list when the linearised set is empty.
    """
    A, b, bounds, free, scale, x0 = _linearised_program(omega_rad_s, g, bound, at, lower, upper, sides, inscribed)
    idx = np.flatnonzero(free)

    def extreme(task):
        k, sign = task
        c = np.zeros(idx.size)
        c[k] = sign
        return task, linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs")

    tasks = [(k, sign) for k in range(idx.size) for sign in (1.0, -1.0)]
    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:  # HiGHS runs outside the GIL
        results = list(pool.map(extreme, tasks))
    out = []
    for (k, sign), res in results:
        if res.status == 2:
            return None
        x = None
        if res.status == 0:
            x = x0.copy()
            x[idx] = x0[idx] + scale * res.x
        out.append((int(idx[k]), sign, x))
    return out


def linearised_extent(omega_rad_s, g, bound, at: np.ndarray, lower: np.ndarray | None = None,
                      upper: np.ndarray | None = None, sides: int = 64, inscribed: bool = True):
    """Per-parameter extent of the feasible set linearised at ``at`` (module docstring).

    Parameters
    ----------
    omega_rad_s, g, bound : arrays (N,)
    at : array (n, 4)
        The linearisation point (the truth, or the identified box's centre).
    lower, upper : arrays (n, 4), optional
        The prior box; parameters with ``lower == upper`` are fixed.
    sides, inscribed : int, bool
        The polygon replacing each disc: inscribed (the reference is never wider than the disc's
        set) or circumscribed (never narrower: never empty where the disc's set is not).

    Returns
    -------
    (lo, hi) arrays (n, 4), or ``None`` when the linearised set is empty (``at`` too far from the
    data for the linearisation to mean anything).
    """
    extremes = linearised_extremes(omega_rad_s, g, bound, at, lower, upper, sides, inscribed)
    if extremes is None:
        return None
    x0 = np.asarray(at, dtype=float).reshape(-1)
    lo_out, hi_out = x0.copy(), x0.copy()
    for p, sign, x in extremes:
        if sign > 0:
            lo_out[p] = -np.inf if x is None else x[p]
        else:
            hi_out[p] = np.inf if x is None else x[p]
    return lo_out.reshape(-1, 4), hi_out.reshape(-1, 4)


def linearised_extent_discs(omega_rad_s, g, bound, at: np.ndarray, lower: np.ndarray, upper: np.ndarray):
    """:func:`linearised_extent` with every disc kept as a disc: each extreme a second-order cone
    program (Clarabel) in place of a polygon's linear program. No polygon error, and a few times
    faster than 64-gons on a few hundred points (the real beam's 384: 15.6 s with 64-gons in
    HiGHS); ``None`` when the linearised set is empty. A solver's answer, not a certificate: a
    diagnostic's reference (``modes[i].exact_ratio``)."""
    import clarabel
    import scipy.sparse as sp

    x0 = np.asarray(at, dtype=float).reshape(-1)
    lower = np.asarray(lower, dtype=float).reshape(-1)
    upper = np.asarray(upper, dtype=float).reshape(-1)
    free = upper > lower
    G, J = model_jacobian(x0, omega_rad_s)
    R = np.asarray(bound, dtype=float)
    keep = np.isfinite(R)
    r, Jf, R = (np.asarray(g, dtype=complex) - G)[keep] / R[keep], J[keep][:, free], R[keep]
    scale = 1.0 / np.maximum(np.max(np.abs(Jf) / R[:, None], axis=0), 1e-300)
    Jf = Jf * scale[None, :] / R[:, None]
    n, p = r.size, int(free.sum())
    # cones (1, Re(r - J u), Im(r - J u)) as s = b - A u; then the box on u
    A_soc = np.zeros((3 * n, p))
    A_soc[1::3], A_soc[2::3] = Jf.real, Jf.imag
    b_soc = np.zeros(3 * n)
    b_soc[0::3], b_soc[1::3], b_soc[2::3] = 1.0, r.real, r.imag
    u_lo, u_hi = (lower[free] - x0[free]) / scale, (upper[free] - x0[free]) / scale
    box_rows = np.vstack([np.eye(p), -np.eye(p)])
    box_b = np.concatenate([u_hi, -u_lo])
    finite = np.isfinite(box_b)
    A = sp.csc_matrix(np.vstack([A_soc, box_rows[finite]]))
    b = np.concatenate([b_soc, box_b[finite]])
    cones = [clarabel.SecondOrderConeT(3) for _ in range(n)] + [clarabel.NonnegativeConeT(int(finite.sum()))]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    lo_out, hi_out = x0.copy(), x0.copy()
    for k, idx in enumerate(np.flatnonzero(free)):
        for sign in (-1.0, 1.0):
            q = np.zeros(p)
            q[k] = -sign
            res = clarabel.DefaultSolver(sp.csc_matrix((p, p)), q, A, b, cones, settings).solve()
            status = str(res.status)
            if "Infeasible" in status and "Dual" not in status:
                return None
            value = x0[idx] + scale[k] * float(res.x[k]) if np.all(np.isfinite(res.x)) else sign * np.inf
            if sign > 0:
                hi_out[idx] = value
            else:
                lo_out[idx] = value
    return lo_out.reshape(-1, 4), hi_out.reshape(-1, 4)
