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
    terms = _CouplingSystem(data, lo, hi, res, unknown, res_unknown)
    choice = terms.initial_choice()
    b, T, rho = terms.system(choice)
    if not rho < 1.0 and terms.m > 1:
        choice, rho = terms.descend(choice, rho)
        b, T, rho = terms.system(choice)
    if not np.isfinite(rho) or rho >= 1.0 or not np.all(np.isfinite(b)):
        raise InputFormatError(
            "prior", "[[mode]]",
            f"cannot bound the residues from the data (mode coupling {rho:.3g} >= 1); give b0_min/b0_max (and b1 = 0 or b1_min/b1_max) for the modes",
        )
    beta = np.linalg.solve(np.eye(terms.m) - T, b)
    beta = beta * (1.0 + 1e-12) + 1e-300  # outward for the rounding of the solve
    if np.any(beta < 0) or not np.all(np.isfinite(beta)):
        raise InputFormatError("prior", "[[mode]]", "cannot bound the residues from the data; give b0_min/b0_max for the modes")
    for r, e in enumerate(terms.entities):
        if e[0] == "res":
            res[e[1]] = [max(res[e[1]][0], -beta[r]), min(res[e[1]][1], beta[r])]
            continue
        k = e[1]
        wj = terms.w[choice[r]]
        # b0 is the real part of N_k(j w_ref), so |b0| <= beta; |b1| w_ref <= beta likewise
        lo[k, B0] = max(lo[k, B0], -beta[r])
        hi[k, B0] = min(hi[k, B0], beta[r])
        if terms.b1_free[k]:
            lo[k, B1] = max(lo[k, B1], -beta[r] / wj)
            hi[k, B1] = min(hi[k, B1], beta[r] / wj)
    return IntervalModel(lo, hi), res


class _CouplingSystem:
    """The unknown terms (modes without residue bounds, unbounded residual terms) and their
    coupling: one point per term gives ``beta <= b + T beta``, solved when ``rho(T) < 1``."""

    def __init__(self, data: FrequencyData, lo: np.ndarray, hi: np.ndarray, res: dict, unknown: np.ndarray, res_unknown: list):
        self.data = data
        w = self.w = data.omega_rad_s
        self.dmax = denominator_max(w[None, :], lo[:, A0, None], hi[:, A0, None], hi[:, A1, None])  # (n, N)
        dmin = denominator_min(w[None, :], lo[:, A0, None], hi[:, A0, None], lo[:, A1, None])
        with np.errstate(divide="ignore"):
            self.inv_dmin = np.where(dmin > 0, 1.0 / np.where(dmin > 0, dmin, 1.0), np.inf)
        # b1 with finite prior bounds enters as the known term max|b1| w; only an unbounded b1 is
        # bounded from the data (|b1| w_ref <= beta)
        self.b1_free = ~(np.isfinite(lo[:, B1]) & np.isfinite(hi[:, B1]))
        # Known modes contribute |N_l(jw)| <= max|b0| + max|b1| w as a constant.
        known_num = np.where(
            unknown[:, None], 0.0,
            np.maximum(np.abs(lo[:, B0]), np.abs(hi[:, B0]))[:, None] + np.maximum(np.abs(lo[:, B1]), np.abs(hi[:, B1]))[:, None] * w[None, :],
        )
        with np.errstate(invalid="ignore"):
            known_term = np.where(unknown[:, None], 0.0, known_num * self.inv_dmin).sum(axis=0)
        self.phis = {name: np.abs(residual_shape(name, w)) for name in res}
        for name, (a, b) in res.items():
            if name not in res_unknown:
                known_term = known_term + max(abs(a), abs(b)) * self.phis[name]
        self.known_term = known_term
        with np.errstate(invalid="ignore"):
            self.fixed_b1 = np.where(self.b1_free, 0.0, np.maximum(np.abs(lo[:, B1]), np.abs(hi[:, B1])))
        # unknown entities: ("mode", k) or ("res", name)
        self.entities = [("mode", int(k)) for k in np.flatnonzero(unknown)] + [("res", name) for name in res_unknown]
        self.m = len(self.entities)

    def own(self, e) -> np.ndarray:
        """Factor turning the right side at each point into a bound on beta_e."""
        return self.dmax[e[1]] if e[0] == "mode" else 1.0 / self.phis[e[1]]

    def contrib(self, e, j: int, w_ref: float) -> float:
        """Contribution of entity e at point j per unit beta_e."""
        if e[0] == "res":
            return float(self.phis[e[1]][j])
        k = e[1]
        scale = 1.0 + (self.w[j] / w_ref if self.b1_free[k] else 0.0)
        return float(scale * self.inv_dmin[k, j])

    def fixed_part(self, e, j: int) -> float:
        """Known b1 terms of the other unknown modes (their b0 is the unknown)."""
        return sum(self.fixed_b1[l] * self.w[j] * self.inv_dmin[l, j] for kind, l in self.entities
                   if kind == "mode" and (kind, l) != e and self.fixed_b1[l] != 0.0)

    def initial_choice(self) -> list[int]:
        """Per term, the point with the smallest own bound among those coupling little."""
        choice = []
        for e in self.entities:
            f = self.own(e)
            others = [x for x in self.entities if x != e]
            if others:
                coupling = f * sum(self.phis[x[1]] if x[0] == "res" else 2.0 * self.inv_dmin[x[1]] for x in others)
            else:
                coupling = np.zeros_like(self.w)
            own_bound = f * (np.abs(self.data.response) + self.data.bound)
            ok = np.isfinite(own_bound) & np.isfinite(coupling) & np.isfinite(self.known_term)
            if not ok.any():
                what = f"[[mode]] {e[1] + 1}" if e[0] == "mode" else "[residuals]"
                hint = "give b0_min/b0_max" if e[0] == "mode" else f"give {e[1]}_min/{e[1]}_max"
                raise InputFormatError("prior", what, f"cannot bound this term from the data (no point away from the other modes' bands); {hint}")
            good = ok & (coupling <= MAX_ROW_COUPLING)
            pool = good if good.any() else ok
            score = np.where(pool, own_bound if good.any() else coupling, np.inf)
            choice.append(int(np.argmin(score)))
        return choice

    def system(self, choice):
        """``(b, T, rho(T))`` of the bound ``beta <= b + T beta`` at the chosen points."""
        data, w, m = self.data, self.w, self.m
        b = np.zeros(m)
        T = np.zeros((m, m))
        for r, e in enumerate(self.entities):
            j = choice[r]
            f = float(self.own(e)[j])
            b[r] = f * (abs(data.response[j]) + data.bound[j] + self.known_term[j] + self.fixed_part(e, j))
            for c, x in enumerate(self.entities):
                if x != e:
                    T[r, c] = f * self.contrib(x, j, w[choice[c]])
        with np.errstate(invalid="ignore", over="ignore"):
            ok = np.all(np.isfinite(T)) and np.all(np.isfinite(b))
            rho = max(abs(np.linalg.eigvals(T))) if (T.size and ok) else (0.0 if ok else np.inf)
        return b, T, rho

    def descend(self, choice: list[int], rho: float) -> tuple[list[int], float]:
        """The greedy per-row choice couples too much: coordinate descent on the spectral radius
        over every point of every row (our addition; any choice gives a valid bound)."""
        choice = list(choice)
        candidates = [np.flatnonzero(np.isfinite(self.own(e)) & np.isfinite(self.known_term)) for e in self.entities]
        for _ in range(4):
            improved = False
            for r in range(self.m):
                best_j, best_rho = choice[r], rho
                for j in candidates[r]:
                    trial = list(choice)
                    trial[r] = int(j)
                    _, _, trial_rho = self.system(trial)
                    if trial_rho < best_rho * (1 - 1e-9):
                        best_j, best_rho = int(j), trial_rho
                if best_j != choice[r]:
                    choice[r], rho, improved = best_j, best_rho, True
            if rho < 0.9 or not improved:
                break
        return choice, rho
