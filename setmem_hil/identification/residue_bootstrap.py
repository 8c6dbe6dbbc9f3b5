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


def bootstrap_residue_bounds(data: FrequencyData, box: IntervalModel) -> IntervalModel:
    """Return ``box`` with every infinite residue bound replaced by a guaranteed finite one."""
    lo, hi = box.lower.copy(), box.upper.copy()
    unknown = ~(np.isfinite(lo[:, B0]) & np.isfinite(hi[:, B0]) & np.isfinite(lo[:, B1]) & np.isfinite(hi[:, B1]))
    if not unknown.any():
        return box
    n = box.n_modes
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
    unknown_idx = np.flatnonzero(unknown)
    # |N_l(jw)| <= beta_l * (1 + w / w_ref_l) for an unknown mode with free b1 (beta_l bounds |N_l(j w_ref)|)
    with np.errstate(invalid="ignore"):
        fixed_b1 = np.where(b1_free, 0.0, np.maximum(np.abs(lo[:, B1]), np.abs(hi[:, B1])))

    def plan(choice):
        """Build (b, T) of beta <= b + T beta for a choice of one point per unknown mode."""
        m = len(unknown_idx)
        b = np.zeros(m)
        T = np.zeros((m, m))
        for r, k in enumerate(unknown_idx):
            j = choice[r]
            others = known_term[j]  # the known modes' contribution at point j
            fixed_part = sum(fixed_b1[l] * w[j] * inv_dmin[l, j] for l in unknown_idx if l != k)
            b[r] = dmax[k, j] * (abs(data.response[j]) + data.bound[j] + others + fixed_part)
            for c, l in enumerate(unknown_idx):
                if l == k:
                    continue
                scale = 1.0 + (w[j] / w[choice[c]] if b1_free[l] else 0.0)
                T[r, c] = dmax[k, j] * scale * inv_dmin[l, j]
        return b, T

    # choose per mode the point with the smallest own bound whose coupling to the others is small
    choice = []
    for k in unknown_idx:
        own = dmax[k] * (np.abs(data.response) + data.bound)
        coupling = dmax[k] * np.sum(inv_dmin[[l for l in unknown_idx if l != k]], axis=0) * 2.0 if len(unknown_idx) > 1 else np.zeros_like(w)
        ok = np.isfinite(own) & np.isfinite(coupling) & np.isfinite(known_term)
        if not ok.any():
            raise InputFormatError("prior", f"[[mode]] {k + 1}", "cannot bound this mode's residue from the data (no point away from the other modes' bands); give b0_min/b0_max")
        good = ok & (coupling <= MAX_ROW_COUPLING)
        pool = good if good.any() else ok
        score = np.where(pool, own if good.any() else coupling, np.inf)
        choice.append(int(np.argmin(score)))
    b, T = plan(choice)
    rho = max(abs(np.linalg.eigvals(T))) if T.size else 0.0
    if not np.isfinite(rho) or rho >= 1.0 or not np.all(np.isfinite(b)):
        raise InputFormatError(
            "prior", "[[mode]]",
            f"cannot bound the residues from the data (mode coupling {rho:.3g} >= 1); give b0_min/b0_max (and b1 = 0 or b1_min/b1_max) for the modes",
        )
    beta = np.linalg.solve(np.eye(len(b)) - T, b)
    for r, k in enumerate(unknown_idx):
        wj = w[choice[r]]
        # b0 is the real part of N_k(j w_ref), so |b0| <= beta; |b1| w_ref <= beta likewise
        lo[k, B0] = max(lo[k, B0], -beta[r])
        hi[k, B0] = min(hi[k, B0], beta[r])
        if b1_free[k]:
            lo[k, B1] = max(lo[k, B1], -beta[r] / wj)
            hi[k, B1] = min(hi[k, B1], beta[r] / wj)
    return IntervalModel(lo, hi)
