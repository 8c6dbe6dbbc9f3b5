"""Guaranteed a-priori bounds on the residues, derived from the data (start of Algorithm 3.1).

The thesis starts Algorithm 3.1 with zero estimates and "a suitable constant determined through
engineering judgment" for the other modes' mismatch (section 3.2.1): not a guarantee. Without
bounds on the residues ``b0_k, b1_k`` the mismatch of Lemma 3.1 is infinite, so we derive
guaranteed bounds first (our choice; the thesis is silent here).

At a point ``w_j`` the data satisfy ``|g_j - sum_k N_k / D_k| <= R_j``, so for one mode k

    |N_k(j w_j)| <= |D_k|max (|g_j| + R_j + sum_{l != k} |N_l(j w_j)| / |D_l|min)

with ``N_k = b0_k + j b1_k w`` and the denominator ranges of eq. (3.34)-(3.35). Using one
well-chosen point ``j(k)`` per mode and ``|N_l(j w)| <= beta_l s_l(w)`` gives the linear system
``beta <= b + T beta`` with ``T >= 0``; when the spectral radius of ``T`` is below one,
``beta <= (I - T)^{-1} b`` (Neumann series), a guaranteed bound. The point chosen for mode k is
near its resonance (small ``|D_k|max``) and far from the others (small coupling ``T``).
"""

from __future__ import annotations

import numpy as np

from setmem_hil.identification.embedding import denominator_max, denominator_min
from setmem_hil.errors import InputFormatError
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import A0, A1, B0, B1, IntervalModel

MAX_ROW_COUPLING = 0.5


def residual_shape(name: str, omega_rad_s) -> np.ndarray:
    """``phi(omega)`` of a residual term ``r phi`` in receptance: ``-1/omega^2`` (lower), ``1`` (upper)."""
    w = np.asarray(omega_rad_s, dtype=float)
    return -1.0 / (w * w) if name == "lower" else np.ones_like(w)


def bootstrap_residue_bounds(data: FrequencyData, box: IntervalModel, residuals: dict | None = None):
    """Return ``box`` with every infinite residue bound replaced by a guaranteed finite one.

    ``residuals`` (optional) maps each enabled residual term (``"lower"``, ``"upper"``) to its
    ``(lo, hi)`` bounds; unbounded ones are bounded in the same linear system (each is one more
    unknown ``beta = |r|`` with ``|r phi(w)|`` its contribution at ``w``). With ``residuals``
    given, returns ``(box, residual_bounds)``.
    """
    residuals = dict(residuals or {})
    out = _bootstrap(data, box, residuals)
    return out if residuals else out[0]


def _bootstrap(data: FrequencyData, box: IntervalModel, residuals: dict):
    lo, hi = box.lower.copy(), box.upper.copy()
    res = {name: [float(a), float(b)] for name, (a, b) in residuals.items()}
    unknown = ~(np.isfinite(lo[:, B0]) & np.isfinite(hi[:, B0]) & np.isfinite(lo[:, B1]) & np.isfinite(hi[:, B1]))
    res_unknown = [name for name, (a, b) in res.items() if not (np.isfinite(a) and np.isfinite(b))]
    if not unknown.any() and not res_unknown:
        return box, res
    w = data.omega_rad_s
    dmax = denominator_max(w[None, :], lo[:, A0, None], hi[:, A0, None], hi[:, A1, None])  # (n, N)
    dmin = denominator_min(w[None, :], lo[:, A0, None], hi[:, A0, None], lo[:, A1, None])
    with np.errstate(divide="ignore"):
        inv_dmin = np.where(dmin > 0, 1.0 / np.where(dmin > 0, dmin, 1.0), np.inf)

    # b1 with finite prior bounds enters as the known term max|b1| w; only an unbounded b1 is
    # bounded from the data (|b1| w_ref <= beta)
    b1_free = ~(np.isfinite(lo[:, B1]) & np.isfinite(hi[:, B1]))
    # Known modes contribute |N_l(jw)| <= max|b0| + max|b1| w as a constant.
    known_num = np.where(
        unknown[:, None], 0.0,
        np.maximum(np.abs(lo[:, B0]), np.abs(hi[:, B0]))[:, None] + np.maximum(np.abs(lo[:, B1]), np.abs(hi[:, B1]))[:, None] * w[None, :],
    )
    with np.errstate(invalid="ignore"):
        known_term = np.where(unknown[:, None], 0.0, known_num * inv_dmin).sum(axis=0)
    phis = {name: np.abs(residual_shape(name, w)) for name in res}
    for name, (a, b) in res.items():
        if name not in res_unknown:
            known_term = known_term + max(abs(a), abs(b)) * phis[name]
    with np.errstate(invalid="ignore"):
        fixed_b1 = np.where(b1_free, 0.0, np.maximum(np.abs(lo[:, B1]), np.abs(hi[:, B1])))
    # unknown entities: ("mode", k) or ("res", name)
    entities = [("mode", int(k)) for k in np.flatnonzero(unknown)] + [("res", name) for name in res_unknown]

    def own(e) -> np.ndarray:
        """Factor turning the right side at each point into a bound on beta_e."""
        return dmax[e[1]] if e[0] == "mode" else 1.0 / phis[e[1]]

    def contrib(e, j: int, w_ref: float) -> float:
        """Contribution of entity e at point j per unit beta_e."""
        if e[0] == "res":
            return float(phis[e[1]][j])
        k = e[1]
        scale = 1.0 + (w[j] / w_ref if b1_free[k] else 0.0)
        return float(scale * inv_dmin[k, j])

    def fixed_part(e, j: int) -> float:
        """Known b1 terms of the other unknown modes (their b0 is the unknown)."""
        return sum(fixed_b1[l] * w[j] * inv_dmin[l, j] for kind, l in entities
                   if kind == "mode" and (kind, l) != e and fixed_b1[l] != 0.0)

    choice = []
    for e in entities:
        f = own(e)
        others = [x for x in entities if x != e]
        if others:
            coupling = f * sum(phis[x[1]] if x[0] == "res" else 2.0 * inv_dmin[x[1]] for x in others)
        else:
            coupling = np.zeros_like(w)
        own_bound = f * (np.abs(data.response) + data.bound)
        ok = np.isfinite(own_bound) & np.isfinite(coupling) & np.isfinite(known_term)
        if not ok.any():
            what = f"[[mode]] {e[1] + 1}" if e[0] == "mode" else "[residuals]"
            hint = "give b0_min/b0_max" if e[0] == "mode" else f"give {e[1]}_min/{e[1]}_max"
            raise InputFormatError("prior", what, f"cannot bound this term from the data (no point away from the other modes' bands); {hint}")
        good = ok & (coupling <= MAX_ROW_COUPLING)
        pool = good if good.any() else ok
        score = np.where(pool, own_bound if good.any() else coupling, np.inf)
        choice.append(int(np.argmin(score)))
    m = len(entities)

    def system(choice):
        b = np.zeros(m)
        T = np.zeros((m, m))
        for r, e in enumerate(entities):
            j = choice[r]
            f = float(own(e)[j])
            b[r] = f * (abs(data.response[j]) + data.bound[j] + known_term[j] + fixed_part(e, j))
            for c, x in enumerate(entities):
                if x != e:
                    T[r, c] = f * contrib(x, j, w[choice[c]])
        with np.errstate(invalid="ignore", over="ignore"):
            ok = np.all(np.isfinite(T)) and np.all(np.isfinite(b))
            rho = max(abs(np.linalg.eigvals(T))) if (T.size and ok) else (0.0 if ok else np.inf)
        return b, T, rho

    b, T, rho = system(choice)
    if not rho < 1.0 and m > 1:
        # the greedy per-row choice couples too much: coordinate descent on the spectral radius
        # over every point of every row (our addition; any choice gives a valid bound)
        candidates = [np.flatnonzero(np.isfinite(own(e)) & np.isfinite(known_term)) for e in entities]
        for _ in range(4):
            improved = False
            for r in range(m):
                best_j, best_rho = choice[r], rho
                for j in candidates[r]:
                    trial = list(choice)
                    trial[r] = int(j)
                    _, _, trial_rho = system(trial)
                    if trial_rho < best_rho * (1 - 1e-9):
                        best_j, best_rho = int(j), trial_rho
                if best_j != choice[r]:
                    choice[r], rho, improved = best_j, best_rho, True
            if rho < 0.9 or not improved:
                break
        b, T, rho = system(choice)
    if not np.isfinite(rho) or rho >= 1.0 or not np.all(np.isfinite(b)):
        raise InputFormatError(
            "prior", "[[mode]]",
            f"cannot bound the residues from the data (mode coupling {rho:.3g} >= 1); give b0_min/b0_max (and b1 = 0 or b1_min/b1_max) for the modes",
        )
    beta = np.linalg.solve(np.eye(m) - T, b)
    beta = beta * (1.0 + 1e-12) + 1e-300  # outward for the rounding of the solve
    if np.any(beta < 0) or not np.all(np.isfinite(beta)):
        raise InputFormatError("prior", "[[mode]]", "cannot bound the residues from the data; give b0_min/b0_max for the modes")
    for r, e in enumerate(entities):
        if e[0] == "res":
            res[e[1]] = [max(res[e[1]][0], -beta[r]), min(res[e[1]][1], beta[r])]
            continue
        k = e[1]
        wj = w[choice[r]]
        # b0 is the real part of N_k(j w_ref), so |b0| <= beta; |b1| w_ref <= beta likewise
        lo[k, B0] = max(lo[k, B0], -beta[r])
        hi[k, B0] = min(hi[k, B0], beta[r])
        if b1_free[k]:
            lo[k, B1] = max(lo[k, B1], -beta[r] / wj)
            hi[k, B1] = min(hi[k, B1], beta[r] / wj)
    return IntervalModel(lo, hi), res
