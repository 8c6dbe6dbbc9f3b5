"""Robust design: a fixed-order compensator tuned to the mixed-mu upper bound of the box.

The thesis designs with H2 (section 6.3.1) on the nominal model and only then measures robust
performance with mixed mu (Definition 2.2). H2 does not see the box it must be robust to. This
module tunes a compensator of the same order to minimise the mixed-mu upper bound itself
(issue 38), starting from the H2 design or from the previous iteration's compensator:

    minimise over K   max_w  lambda_max( H_w(K) ),   H_w = M_D^* M_D + j (G M_D - M_D^* G)   (eq. 2.15)

with ``M = F_l(P, K)`` the closed loop of eq. (6.23) and the scalings ``D, G`` of each frequency
held fixed during an inner step (any ``D > 0``, real ``G`` gives a valid upper bound at its
frequency, so the inner objective is always a true bound there). An outer step re-solves ``D, G``
at the new compensator (:func:`~setmem_hil.robust.mixed_mu.mixed_mu_upper`). This is the
"D-K" alternation with the K step done directly on the bound instead of by H-infinity synthesis:
it keeps the compensator's order (D-K with fitted scalings gave order 55, issue 38) and treats the
real blocks as real.

Inner step (ours): the nonsmooth max over frequencies and over (often repeated) top eigenvalues
is smoothed by ``f_tau = tau log sum_{w, i} exp(lambda_{w,i} / tau)`` over the top eigenvalues of
every frequency, minimised by BFGS with a backtracking line search that refuses any step leaving
the nominal closed loop unstable or the trust region. Its gradient is analytic: with ``u_i`` an
eigenvector of ``H_w``, ``d lambda_i = 2 Re(u_i^* (M_D^* + j G) dM_D u_i)`` (Theorem 4.2 applied to
``H``), ``dM = P_12 P_21 dk / (1 - P_22 k)^2`` for positive feedback ``u = K y`` and
``dk = C_K R dA_K R B_K + C_K R dB_K + dC_K R B_K + dD_K``, ``R = (j w I - A_K)^{-1}``.

Parameterisation: every entry of ``(A_K, B_K, C_K, D_K)`` of a *balanced* realisation of the
start (its Gramians equal and diagonal). A modal form of these lightly damped compensators is
ill-conditioned (0.04 % on one entry destabilised a loop, issue 38); the balanced form spreads the
sensitivity evenly. An unstable start (H2 compensators can be) keeps its real Schur form.

Frequency set: the analysis grid, plus the frequencies of the closed loop's lightly damped poles
and points between the neighbours of every local maximum near the peak, accumulated over the
outer steps (a peak that appears between grid points is added and kept). A step is accepted only
if the peak over that set falls. The final compensator is then analysed, certified on the whole
band and put through the safeguard of eq. (5.12) by the caller, exactly as an H2 design is.

Everything here works in the analysis's normalised time and magnitude
(:func:`~setmem_hil.robust.analysis.analyze_robust_performance`).
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg import schur, solve_continuous_lyapunov

from setmem_hil.numerics.blas_threads import single_thread_blas
from setmem_hil.robust.augmented_plant import AugmentedPlant, StateSpaceMatrices
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper, rounding_margin, scaled_hermitian

__all__ = ["DESIGN_METHODS", "FINAL_TUNING", "TuningSettings", "TuningResult", "tune_compensator", "balanced_realisation"]

DESIGN_METHODS = ("robust", "h2")


@dataclass(frozen=True)
class TuningSettings:
    """Effort of :func:`tune_compensator` (defaults chosen on the 6.3.2 campaign's boxes).

    Only counts limit the effort, never the wall clock: a resumed campaign must make the same
    choices on any machine (the journal's replay check).

    Attributes
    ----------
    max_outer : int
        Outer steps (a re-solve of the scalings each).
    inner_iterations : int
        BFGS iterations per inner step.
    smoothing : float
        ``tau`` of the log-sum-exp relative to the squared peak at the start; a step the true peak
        refuses divides it by 3 (down to :data:`MIN_SMOOTHING`), so a smoothed peak biased by many
        frequencies near the top cannot stall the descent.
    min_gain : float
        Stop when an accepted outer step lowers the peak by less than this fraction.
    refresh_window : float
        After a step, the scalings are solved again where the stale bound is within this fraction
        of its peak (elsewhere the stale bound, still valid, is kept).
    rounds : int
        Tunings per design: after each, the analysis (grid refinement and certificate) runs, and
        where it found mu-bar above the tuned peak those frequencies join the set and the tuning
        goes on (:func:`~setmem_hil.robust.analysis.analyze_robust_performance`).
    active_fraction : float
        An inner step sees the frequencies whose bound is at least this fraction of the peak
        (``lambda_max`` units); the others are checked when the step is judged.
    """

    max_outer: int = 5
    inner_iterations: int = 30
    smoothing: float = 3e-3
    min_gain: float = 2e-3
    refresh_window: float = 0.15
    active_fraction: float = 0.05
    rounds: int = 1


MIN_SMOOTHING = 1e-5  # relative tau below which the log-sum-exp is the plain maximum to rounding

FINAL_TUNING = TuningSettings(max_outer=12, inner_iterations=40, min_gain=5e-4, rounds=3)
"""The effort spent once the goal is reached: the delivered compensator's margin (issue 38)."""


@dataclass(frozen=True)
class TuningResult:
    """Outcome of :func:`tune_compensator`.

    Attributes
    ----------
    controller : StateSpaceMatrices
        The tuned compensator (positive feedback ``u = K y``), or the start when nothing improved.
    start_peak, peak : float
        Peak of the mixed-mu upper bound over the frequency set at the start and at the end.
    outer_steps, evaluations : int
        Work done (outer steps tried, objective evaluations).
    improved : bool
        Whether any step was accepted (else ``controller`` is the start).
    start_index : int
        Which of the starts the tuning began from (the one with the lowest peak).
    """

    controller: StateSpaceMatrices
    start_peak: float
    peak: float
    outer_steps: int
    evaluations: int
    improved: bool
    start_index: int = 0


def _matrices(K) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    A = np.atleast_2d(np.asarray(K.A, dtype=float))
    n = A.shape[0] if A.size else 0
    A = A.reshape(n, n)
    B = np.asarray(K.B, dtype=float).reshape(n, 1)
    C = np.asarray(K.C, dtype=float).reshape(1, n)
    D = np.asarray(K.D, dtype=float).reshape(1, 1)
    return A, B, C, D


def balanced_realisation(K) -> StateSpaceMatrices:
    """A balanced realisation of a stable SISO compensator (square-root method); an unstable one
    in real Schur form. The transfer function is unchanged."""
    A, B, C, D = _matrices(K)
    n = A.shape[0]
    if n == 0:
        return StateSpaceMatrices(A, B, C, D)
    if np.max(np.linalg.eigvals(A).real) < 0.0:
        try:
            Wc = solve_continuous_lyapunov(A, -B @ B.T)
            Wo = solve_continuous_lyapunov(A.T, -C.T @ C)
            jitter = 1e-13 * np.eye(n)
            Lc = np.linalg.cholesky(0.5 * (Wc + Wc.T) + jitter * np.trace(Wc))
            Lo = np.linalg.cholesky(0.5 * (Wo + Wo.T) + jitter * np.trace(Wo))
            U, s, Vt = np.linalg.svd(Lo.T @ Lc)
            if s.min() > 1e-12 * s.max():
                T = Lc @ Vt.T / np.sqrt(s)
                Ti = (U / np.sqrt(s)).T @ Lo.T
                return StateSpaceMatrices(Ti @ A @ T, Ti @ B, C @ T, D)
        except np.linalg.LinAlgError:
            pass
    Ts, Z = schur(A, output="real")
    return StateSpaceMatrices(Ts, Z.T @ B, C @ Z, D)


class _OpenLoopResponse:
    """``P_11, P_12, P_21, P_22`` of the augmented plant at a set of frequencies."""

    def __init__(self, plant: AugmentedPlant, omega: np.ndarray):
        B = np.hstack([plant.Bw, plant.Bu])
        C = np.vstack([plant.Cz, plant.Cy])
        D = np.block([[plant.Dzw, plant.Dzu], [plant.Dyw, np.zeros((1, 1))]])
        R = StateSpaceMatrices(plant.A, B, C, D).frequency_response(omega)
        nz, nw = plant.Cz.shape[0], plant.Bw.shape[1]
        self.omega = omega
        self.P11, self.P12, self.P21, self.P22 = R[:, :nz, :nw], R[:, :nz, nw], R[:, nz, :nw], R[:, nz, nw]


class _Objective:
    """The smoothed bound ``f_tau`` and its gradient over the compensator's entries."""

    N_TOP = 4  # eigenvalues per frequency in the log-sum-exp (the top is often repeated at optimal D, G)

    def __init__(self, response: _OpenLoopResponse, d: np.ndarray, g: np.ndarray, nk: int, tau: float):
        self.r, self.d, self.g, self.nk, self.tau = response, d, g, nk, tau
        self.evaluations = 0

    def __call__(self, theta: np.ndarray):
        """``(f_tau, peak lambda_max, gradient)``."""
        self.evaluations += 1
        r, nk = self.r, self.nk
        A, B, C, D = _unpack(theta, nk)
        jw = 1j * r.omega
        lhs = jw[:, None, None] * np.eye(nk) - A
        RB = np.linalg.solve(lhs, np.broadcast_to(B.astype(complex)[:, None], (jw.size, nk, 1)))[:, :, 0]
        CR = np.linalg.solve(np.swapaxes(lhs, 1, 2), np.broadcast_to(C.astype(complex)[:, None], (jw.size, nk, 1)))[:, :, 0]
        k = RB @ C + D
        den = 1.0 - r.P22 * k
        M = r.P11 + (r.P12 / den[:, None])[:, :, None] * (k[:, None] * r.P21)[:, None, :]
        lam, U = _eigh(scaled_hermitian(M, self.d, self.g))
        lam, U = lam[:, -self.N_TOP:], U[:, :, -self.N_TOP:]
        top = lam.max()
        e = np.exp((lam - top) / self.tau)
        f = top + self.tau * np.log(e.sum())
        weights = e / e.sum()
        n = self.d.shape[1]
        MD = M * (self.d[:, :, None] / self.d[:, None, :])
        Q = np.conj(np.swapaxes(MD, 1, 2)) + 1j * self.g[:, :, None] * np.eye(n)
        left = np.einsum("wji,wjk,wk->wi", np.conj(U), Q, self.d * r.P12)
        right = np.einsum("wk,wki->wi", r.P21 / self.d, U)
        c = (weights * left * right).sum(axis=1) / den**2  # d f / d k(j w), per frequency
        gA = 2.0 * np.real(np.einsum("w,wi,wj->ij", c, CR, RB))
        grad = np.concatenate([gA.ravel(), 2.0 * np.real(c @ CR), 2.0 * np.real(c @ RB), [2.0 * np.real(c.sum())]])
        return f, float(lam[:, -1].max()), grad


@lru_cache(maxsize=1)
def _pool() -> ThreadPoolExecutor:
    """Two workers: numpy's batched eigensolvers release the GIL, so halves of the frequency
    axis run on both cores (the computation per frequency is the same either way). Each half
    runs with single-threaded BLAS (:mod:`setmem_hil.numerics.blas_threads`: the setting is per
    thread, and two threads of multithreaded OpenBLAS on two cores slow each other down)."""
    return ThreadPoolExecutor(max_workers=2, thread_name_prefix="robust-design")


def _halves(n: int) -> list[slice]:
    if n < 64 or (os.cpu_count() or 1) < 2:
        return [slice(0, n)]
    return [slice(0, n // 2), slice(n // 2, n)]


def _eigh(H: np.ndarray):
    """``numpy.linalg.eigh`` of a stack, the halves of the stack in two threads."""
    parts = _halves(H.shape[0])
    if len(parts) == 1:
        return np.linalg.eigh(H)
    done = list(_pool().map(single_thread_blas(lambda sl: np.linalg.eigh(H[sl])), parts))
    return np.concatenate([p[0] for p in done]), np.concatenate([p[1] for p in done])


def _mu_upper(M: np.ndarray, structure: MuStructure):
    """The scalings of :func:`mixed_mu_upper` (short run), the stack's halves in two threads."""
    parts = _halves(M.shape[0])
    done = list(_pool().map(single_thread_blas(lambda sl: mixed_mu_upper(M[sl], structure, tol=1e-3, max_iter=30)), parts))
    return np.concatenate([b.beta for b in done]), np.concatenate([b.d for b in done]), np.concatenate([b.g for b in done])


def _bfgs(fun, x0: np.ndarray, acceptable, max_iter: int) -> tuple[np.ndarray, bool]:
    """BFGS with Armijo backtracking; ``acceptable(x)`` vetoes a trial point (instability, trust
    region). Returns the last accepted point and whether any step was taken."""
    f, _, g = fun(x0)
    x, n, moved = x0.copy(), x0.size, False
    H = np.eye(n) * (1e-2 / max(np.linalg.norm(g), 1e-300))
    for it in range(max_iter):
        p = -H @ g
        slope = float(p @ g)
        if not slope < 0.0:
            H = np.eye(n) * (1e-2 / max(np.linalg.norm(g), 1e-300))
            p, slope = -H @ g, float(-(H @ g) @ g)
        t, found = 1.0, False
        for _ in range(20):
            xn = x + t * p
            if acceptable(xn):
                fn, _, gn = fun(xn)
                if fn <= f + 1e-4 * t * slope:
                    found = True
                    break
            t *= 0.3
        if not found:
            break
        s, y = xn - x, gn - g
        sy = float(s @ y)
        if sy > 1e-300:
            if it == 0:
                H = np.eye(n) * (sy / float(y @ y))
            rho, Hy = 1.0 / sy, H @ y
            H = H - rho * (np.outer(s, Hy) + np.outer(Hy, s)) + (rho * rho * float(y @ Hy) + rho) * np.outer(s, s)
        x, f, g, moved = xn, fn, gn, True
    return x, moved


def _spectral_abscissa(plant: AugmentedPlant, K: StateSpaceMatrices) -> float:
    return float(np.max(np.linalg.eigvals(plant.closed_loop(K).A).real))


def _lightly_damped_frequencies(cl: StateSpaceMatrices, band: tuple[float, float]) -> np.ndarray:
    """Natural frequencies (x 0.98, 1, 1.02) and damped frequencies of the closed loop's poles with damping below 0.2."""
    ev = np.linalg.eigvals(cl.A)
    ev = ev[(ev.imag > 0.0) & (np.abs(ev.real) < 0.2 * np.abs(ev))]
    pts = np.concatenate([np.abs(ev) * f for f in (0.98, 1.0, 1.02)] + [ev.imag])
    return pts[(pts >= band[0]) & (pts <= band[1])]


def _around_local_peaks(omega: np.ndarray, beta: np.ndarray, window: float = 0.03, n_points: int = 4, most: int = 4) -> np.ndarray:
    """Points between the neighbours of the (at most ``most``) highest local maxima within
    ``window`` of the peak."""
    if omega.size < 3:
        return np.zeros(0)
    top = beta.max()
    inner = np.flatnonzero((beta[1:-1] >= beta[:-2]) & (beta[1:-1] >= beta[2:]) & (beta[1:-1] >= (1.0 - window) * top)) + 1
    inner = inner[np.argsort(beta[inner])[::-1][:most]]
    pts = [np.geomspace(omega[i - 1], omega[i + 1], n_points + 2)[1:-1] for i in inner]
    return np.concatenate(pts) if pts else np.zeros(0)


def _not_near(existing: np.ndarray, candidates: np.ndarray, rtol: float = 2e-3) -> np.ndarray:
    """The candidates farther than ``rtol`` (relative) from every existing frequency: the set
    grows only where it has no point yet."""
    candidates = np.unique(candidates)
    if existing.size == 0 or candidates.size == 0:
        return candidates
    pos = np.clip(np.searchsorted(existing, candidates), 1, existing.size - 1)
    gap = np.minimum(np.abs(existing[pos] - candidates), np.abs(existing[pos - 1] - candidates))
    return candidates[gap > rtol * candidates]


class _ScaledSet:
    """Frequencies with their scalings ``D, G`` and the bound they give at a compensator."""

    def __init__(self, plant: AugmentedPlant, structure: MuStructure, K: StateSpaceMatrices, omega: np.ndarray):
        self.plant, self.structure = plant, structure
        self.omega = np.zeros(0)
        self.d = np.zeros((0, structure.size))
        self.g = np.zeros((0, structure.size))
        self.add(K, omega)

    def add(self, K: StateSpaceMatrices, omega: np.ndarray) -> None:
        new = _not_near(self.omega, np.asarray(omega, dtype=float))
        if new.size == 0:
            return
        _, d, g = _mu_upper(self.plant.closed_loop(K).frequency_response(new), self.structure)
        order = np.argsort(np.concatenate([self.omega, new]))
        self.omega = np.concatenate([self.omega, new])[order]
        self.d = np.concatenate([self.d, d])[order]
        self.g = np.concatenate([self.g, g])[order]

    def stale_bound(self, K: StateSpaceMatrices) -> np.ndarray:
        """``lambda_max`` (with its rounding margin) at the stored scalings: valid at ``K`` too."""
        H = scaled_hermitian(self.plant.closed_loop(K).frequency_response(self.omega), self.d, self.g)
        return np.linalg.eigvalsh(H)[:, -1] + rounding_margin(H)

    def follow(self, K: StateSpaceMatrices, band: tuple[float, float]) -> None:
        """Add the loop's lightly damped poles, then points around its local peaks."""
        self.add(K, _lightly_damped_frequencies(self.plant.closed_loop(K), band))
        self.add(K, _around_local_peaks(self.omega, self.stale_bound(K)))

    def refresh_near_peak(self, K: StateSpaceMatrices, window: float) -> None:
        """:meth:`refresh` where the stale bound is within ``window`` of its peak."""
        stale = self.stale_bound(K)
        self.refresh(K, stale >= (1.0 - window) * stale.max())

    def refresh(self, K: StateSpaceMatrices, where: np.ndarray) -> None:
        """Solve the scalings again at the frequencies ``where`` (a boolean mask), keeping the new
        ones only where they give a lower bound."""
        idx = np.flatnonzero(where)
        if idx.size == 0:
            return
        M = self.plant.closed_loop(K).frequency_response(self.omega[idx])
        beta, d, g = _mu_upper(M, self.structure)
        old = np.linalg.eigvalsh(scaled_hermitian(M, self.d[idx], self.g[idx]))[:, -1]
        better = beta**2 <= old
        self.d[idx[better]] = d[better]
        self.g[idx[better]] = g[better]


def tune_compensator(
    plant: AugmentedPlant,
    start,
    omega: np.ndarray,
    settings: TuningSettings = TuningSettings(),
) -> TuningResult:
    """Tune a compensator of the start's order to minimise the mixed-mu upper bound (module doc).

    Parameters
    ----------
    plant : AugmentedPlant
        ``P`` of eq. (6.20)-(6.22) (normalised units).
    start : StateSpace-like or sequence of them
        The compensator(s) to start from (``A, B, C, D``; positive feedback); the one stabilising
        ``P`` with the lowest peak is tuned (the H2 design and the previous iteration's compensator).
    omega : numpy.ndarray
        The analysis grid (rad/s, normalised).
    settings : TuningSettings

    Returns
    -------
    TuningResult
        Never worse than the start over the frequency set (a step is kept only if the peak falls).
    """
    structure = MuStructure(plant.n_real, plant.n_complex)
    band = (float(omega.min()), float(omega.max()))
    K, freq, best_peak, chosen = _best_start(plant, structure, start, omega, band)
    nk = K.n_states
    start_peak, evaluations, outer, improved = best_peak, 0, 0, False
    theta = _pack(K)
    radius = 0.5 * max(np.linalg.norm(theta), 1e-12)
    smoothing = settings.smoothing
    while outer < settings.max_outer:
        outer += 1
        # the objective sees the frequencies that can become the peak within a step; the rest
        # are checked (with their still valid stale bound) when the step is judged
        stale = freq.stale_bound(_as_matrices(theta, nk))
        active = stale >= settings.active_fraction * stale.max()
        objective = _Objective(_OpenLoopResponse(plant, freq.omega[active]), freq.d[active], freq.g[active], nk,
                               smoothing * best_peak)
        centre = theta.copy()

        def acceptable(x: np.ndarray) -> bool:
            return bool(np.linalg.norm(x - centre) <= radius) and _spectral_abscissa(plant, _as_matrices(x, nk)) < 0.0

        trial, moved = _bfgs(objective, theta, acceptable, settings.inner_iterations)
        evaluations += objective.evaluations
        if not moved:
            break
        Kt = _as_matrices(trial, nk)
        # the frequency set follows the trial loop: its lightly damped poles and new local peaks
        freq.follow(Kt, band)
        freq.refresh_near_peak(Kt, settings.refresh_window)
        peak = float(freq.stale_bound(Kt).max())
        if peak < best_peak:
            gain = (best_peak - peak) / best_peak
            theta, best_peak, improved = trial, peak, True
            if gain < settings.min_gain:
                break
        else:  # a peak the inner step did not see: it is in the set now; retry shorter
            freq.refresh_near_peak(_as_matrices(theta, nk), settings.refresh_window)
            radius *= 0.5
            smoothing = max(0.3 * smoothing, MIN_SMOOTHING)  # the smoothed peak's bias hid the true one
    return TuningResult(_as_matrices(theta, nk), math.sqrt(max(start_peak, 0.0)), math.sqrt(max(best_peak, 0.0)), outer, evaluations, improved, chosen)


def _best_start(plant: AugmentedPlant, structure: MuStructure, starts, omega: np.ndarray, band):
    """The start (of those stabilising the nominal loop) with the lowest peak over its frequency
    set: ``(balanced K, its scaled set, peak lambda, index)``."""
    starts = list(starts) if isinstance(starts, (list, tuple)) else [starts]
    best = None
    for i, start in enumerate(starts):
        K = balanced_realisation(start)
        if _spectral_abscissa(plant, K) >= 0.0:
            continue
        # the grid and the loop's lightly damped poles solved as one stack, then the local peaks
        freq = _ScaledSet(plant, structure, K, np.concatenate([omega, _lightly_damped_frequencies(plant.closed_loop(K), band)]))
        freq.add(K, _around_local_peaks(freq.omega, freq.stale_bound(K)))
        peak = float(freq.stale_bound(K).max())
        if best is None or peak < best[2]:
            best = (K, freq, peak, i)
    if best is None:
        raise ValueError("tune_compensator: no start stabilises the nominal loop")
    return best


def _pack(K: StateSpaceMatrices) -> np.ndarray:
    """The tuning's variables: every entry of ``(A, B, C, D)``."""
    return np.concatenate([K.A.ravel(), K.B.ravel(), K.C.ravel(), K.D.ravel()])


def _unpack(theta: np.ndarray, nk: int):
    """``(A, B, C, D)`` views of the variables of an order-``nk`` compensator (``B``, ``C`` flat)."""
    A = theta[: nk * nk].reshape(nk, nk)
    B = theta[nk * nk: nk * nk + nk]
    C = theta[nk * nk + nk: nk * nk + 2 * nk]
    return A, B, C, theta[-1]


def _as_matrices(theta: np.ndarray, nk: int) -> StateSpaceMatrices:
    A, B, C, D = _unpack(theta, nk)
    return StateSpaceMatrices(A.copy(), B.reshape(nk, 1).copy(), C.reshape(1, nk).copy(), np.array([[float(D)]]))
