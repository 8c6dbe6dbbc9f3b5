"""Checking a robust-performance claim plant by plant (issue 27, ``setmem-hil validate``).

For one *fixed* plant ``G`` the structured problem of chapter 2 leaves two complex scalar blocks:
the additive unmodelled dynamics ``Delta_1`` (``y = G u + w_1``, ``z_1 = W_1 u``) and the
performance block (``z_2 = W_2 y``), both entering at the output (eq. 6.20-6.22). With the
positive feedback ``u = K y`` the closed loop from ``(w_1, w_2)`` to ``(z_1, z_2)`` is the rank-one
matrix ``[W_1 K S; W_2 S] [1 1]`` with ``S = 1 / (1 - G K)``, whose structured singular value
is exactly

    mu(omega) = |W_2 S| + |W_1 K S|,

so robust performance holds for that plant iff the closed loop is stable and ``max_omega mu < 1``.
A mixed-mu upper bound below 1 over the interval box claims exactly this for every plant in the
box; any plant with a peak >= 1 falsifies the claim. Pure numerics (no I/O).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import qmc

from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.model.weights import Weights

__all__ = ["PlantCheck", "rp_curve", "rp_peak", "closed_loop_stable", "box_plants", "closed_loop_simulation", "MAX_VERTICES"]

MAX_VERTICES = 4096  # 2^12; a larger box is sampled by a Latin hypercube of this size


@dataclass(frozen=True)
class PlantCheck:
    stable: bool
    rp_peak: float
    rp_peak_omega: float


def _polyval(coeffs, s):
    return np.polyval(np.asarray(coeffs, dtype=float), s)


def _controller_response(K, omega: np.ndarray) -> np.ndarray:
    A, B, C, D = (np.atleast_2d(np.asarray(getattr(K, n), dtype=float)) for n in "ABCD")
    n = A.shape[0]
    out = np.empty(omega.size, complex)
    for i, w in enumerate(omega):
        out[i] = (C @ np.linalg.solve(1j * w * np.eye(n) - A, B) + D)[0, 0] if n else D[0, 0]
    return out


def rp_curve(plant: ModalParameters, K, weights: Weights, omega: np.ndarray, k_response: np.ndarray | None = None) -> np.ndarray:
    """``|W_2 S| + |W_1 K S|`` at ``omega`` (rad/s) for one plant (module docstring)."""
    omega = np.asarray(omega, dtype=float)
    s = 1j * omega
    g = np.ravel(plant.frequency_response(omega))
    k = _controller_response(K, omega) if k_response is None else k_response
    w1 = _polyval(weights.w1_num, s) / _polyval(weights.w1_den, s)
    w2_num, w2_den = weights.w2_for_design()  # the W2 of the analysis (section 6.3.1's roll-off pole)
    w2 = _polyval(w2_num, s) / _polyval(w2_den, s)
    sens = 1.0 / (1.0 - g * k)
    return np.abs(w2 * sens) + np.abs(w1 * k * sens)


def rp_peak(plant: ModalParameters, K, weights: Weights, grid: np.ndarray, k_on_grid: np.ndarray | None = None,
            refine: int = 3) -> tuple[float, float]:
    """Peak of :func:`rp_curve` over the band of ``grid``: the dense grid, then a bounded
    scalar search between the neighbours of its ``refine`` largest local maxima."""
    values = rp_curve(plant, K, weights, grid, k_on_grid)
    best = int(np.argmax(values))
    peak, where = float(values[best]), float(grid[best])
    interior = np.flatnonzero((values[1:-1] >= values[:-2]) & (values[1:-1] >= values[2:])) + 1
    for i in interior[np.argsort(values[interior])[::-1][:refine]]:
        lo, hi = math.log(grid[i - 1]), math.log(grid[i + 1])
        res = minimize_scalar(lambda x: -float(rp_curve(plant, K, weights, np.array([math.exp(x)]))[0]), bounds=(lo, hi),
                              method="bounded", options={"xatol": 1e-10})
        if -res.fun > peak:
            peak, where = float(-res.fun), float(math.exp(res.x))
    return peak, where


def closed_loop_stable(plant: ModalParameters, K) -> bool:
    """Internal stability of ``u = K y`` around ``plant`` (positive feedback)."""
    return bool(np.max(np.linalg.eigvals(closed_loop_matrix(plant, K)).real) < 0.0)


def closed_loop_matrix(plant: ModalParameters, K) -> np.ndarray:
    """The state matrix of ``u = K y`` around ``plant`` (positive feedback)."""
    Ap, Bp, Cp, _ = plant.state_space_matrices()
    Ak, Bk, Ck, Dk = (np.atleast_2d(np.asarray(getattr(K, n), dtype=float)) for n in "ABCD")
    nk = Ak.shape[0] if Ak.size else 0
    top = np.hstack([Ap + Bp @ Dk @ Cp, Bp @ Ck]) if nk else Ap + Bp @ Dk @ Cp
    return np.vstack([top, np.hstack([Bk @ Cp, Ak])]) if nk else top


def box_plants(model: IntervalModel, n_random: int, seed: int = 0) -> tuple[np.ndarray, str]:
    """Parameter arrays ``(n, n_modes, 4)``: every vertex of the box (up to ``MAX_VERTICES``,
    else a Latin hypercube of that many) plus ``n_random`` uniform points; and how the first
    part was drawn (``"vertices"`` or ``"latin-hypercube"``)."""
    lo, hi = model.lower, model.upper
    free = np.argwhere(hi > lo)
    rng = np.random.default_rng(seed)
    if 2 ** len(free) <= MAX_VERTICES:
        corners = np.array(list(itertools.product((0.0, 1.0), repeat=len(free)))) if len(free) else np.zeros((1, 0))
        how = "vertices"
    else:
        corners = qmc.LatinHypercube(d=len(free), seed=rng).random(MAX_VERTICES)
        how = "latin-hypercube"
    unit = np.vstack([corners, rng.random((n_random, len(free)))])
    plants = np.repeat(lo[None, :, :], unit.shape[0], axis=0)
    for j, (i, p) in enumerate(free):
        plants[:, i, p] = lo[i, p] + unit[:, j] * (hi[i, p] - lo[i, p])
    return plants, how


MAX_SIMULATION_STEPS = 400_000


def closed_loop_simulation(truth: ModalParameters, continuous, discrete, weights: Weights, omega_rad_s: float) -> dict:
    """The sampled loop in the time domain: the true structure (zero-order hold at the
    compensator's period) under the discrete compensator, a unit sinusoidal disturbance at the
    performance input (the output, ``w_2``) at ``omega_rad_s``. The steady-state amplitudes of
    ``y`` and ``u`` give the measured ``|W_2 S| + |W_1 K S|`` there, compared with the
    frequency-domain value of the continuous loop.
    """
    import scipy.signal

    Ts = float(discrete.dt)
    Ap, Bp, Cp, Dp = truth.state_space_matrices()
    Ad, Bd, _, _, _ = scipy.signal.cont2discrete((Ap, Bp, Cp, Dp), Ts, method="zoh")
    Ak, Bk, Ck, Dk = (np.atleast_2d(np.asarray(getattr(discrete, n), dtype=float)) for n in "ABCD")
    n, nk = Ad.shape[0], Ak.shape[0]
    A = np.block([[Ad + Bd @ Dk @ Cp, Bd @ Ck], [Bk @ Cp, Ak]])
    B = np.vstack([Bd @ Dk, Bk])
    C = np.vstack([np.hstack([Cp, np.zeros((1, nk))]), np.hstack([Dk @ Cp, Ck])])  # outputs y and u
    D = np.vstack([np.ones((1, 1)), Dk])
    radius = float(np.max(np.abs(np.linalg.eigvals(A))))
    if radius >= 1.0:
        return {"stable": False, "fs_hz": 1.0 / Ts, "omega_rad_s": omega_rad_s}
    period = 2 * math.pi / omega_rad_s
    settle = 10.0 * Ts / max(-math.log(radius), 1e-12)
    steps = int(min(MAX_SIMULATION_STEPS, math.ceil((settle + 40 * period) / Ts)))
    t = np.arange(steps) * Ts
    d = np.sin(omega_rad_s * t)
    x = np.zeros(n + nk)
    out = np.empty((steps, 2))
    for k in range(steps):  # the sampled loop, step by step, as the target runs it
        out[k] = C @ x + D[:, 0] * d[k]
        x = A @ x + B[:, 0] * d[k]
    tail = t >= t[-1] - 20 * period
    basis = np.column_stack([np.sin(omega_rad_s * t[tail]), np.cos(omega_rad_s * t[tail])])
    amp = [float(np.hypot(*np.linalg.lstsq(basis, out[tail, i], rcond=None)[0])) for i in range(2)]
    measured = float(weights.w2_magnitude(omega_rad_s)) * amp[0] + float(weights.w1_magnitude(omega_rad_s)) * amp[1]
    predicted = float(rp_curve(truth, continuous, weights, np.array([omega_rad_s]))[0])  # the continuous loop
    return {"stable": True, "fs_hz": 1.0 / Ts, "omega_rad_s": float(omega_rad_s), "duration_s": float(steps * Ts),
            "settled": bool(steps < MAX_SIMULATION_STEPS), "measured": float(measured), "S_amplitude": amp[0],
            "KS_amplitude": amp[1], "predicted": predicted, "relative_difference": abs(measured / predicted - 1.0)}
