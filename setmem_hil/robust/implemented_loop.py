"""mu-bar of the loop as a real-time target runs it: the discrete sections, the computation
delay and the zero-order hold (issue 45).

A target samples ``y`` every ``Ts = 1 / fs``, runs the compensator's sections
(:func:`~setmem_hil.robust.controller_forms.second_order_sections`, Tustin prewarped at the
mu-bar peak), writes ``u[k]`` computed from ``y[k - D]`` (``D = delay_samples``) and holds it
until the next sample. At a frequency ``w`` below Nyquist, the drive's component at ``w`` is the
sensor's times the **implemented compensator**

    K_impl(jw) = K_d(exp(jwTs)) * exp(-jwTs D) * (1 - exp(-jwTs)) / (jwTs),

the discrete sections, the delay, and the hold (sampler ``1/Ts`` times the hold
``(1 - exp(-sTs))/s``). The loop is then thesis eq. (6.16)-(6.22) with ``K`` replaced by
``K_impl``: ``M(jw) = P_zw + P_zu K (1 - P_yu K)^-1 P_yw`` (positive feedback), and mu-bar is the
same D,G-scaled upper bound (Definition 2.2) on the same structure.

**What is approximated, said plainly.** The hold also puts the drive's images at
``w + k 2pi/Ts`` into the structure, and the sampler folds the response at those images back to
``w``. They are left out: the structure is low-pass and lightly damped far below Nyquist, so its
response at the images is small; :attr:`ImplementedLoop.image_ratio` reports the largest ratio
``|G(j(2pi/Ts - w))| / |G(jw)|`` (the first image, through the nominal structure) over the
frequencies that decide mu-bar (within 10 % of its peak), so a sample rate where it is not small
is visible. The band is evaluated on a grid
(the analysis's default grid below Nyquist, refined twice around the peak), not band-certified
as the continuous loop is: a delay has no finite state space for the certificate's test. Nominal
stability is checked exactly, on the sampled loop (the nominal structure discretised with the
hold, the sections, the delay line): an unstable one has mu-bar infinite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import Weights
from setmem_hil.numerics.zero_order_hold import held
from setmem_hil.robust.augmented_plant import AugmentedPlant, augmented_plant
from setmem_hil.robust.controller_forms import second_order_sections
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper
from setmem_hil.robust.uncertain_plant import uncertain_plant

__all__ = ["ImplementedLoop", "implemented_response", "implemented_mu_bar", "required_sample_rate", "NYQUIST_FRACTION"]

NYQUIST_FRACTION = 0.95
"""The band evaluated ends here (a fraction of Nyquist): the hold's images meet the band at Nyquist."""
PRECISE_TOL, PRECISE_MAX_ITER = 1e-7, 100
IMAGE_CHECK_LEVEL = 0.9
"""The image ratio is reported over the frequencies where mu is within 10 % of its peak."""


@dataclass(frozen=True)
class ImplementedLoop:
    """mu-bar of the loop as the target runs it (see the module docstring)."""

    fs_hz: float
    delay_samples: int
    prewarp_rad_s: float
    mu_bar: float
    mu_bar_omega_rad_s: float
    nominally_stable: bool
    image_ratio: float
    omega_rad_s: np.ndarray
    mu: np.ndarray

    def to_document(self) -> dict:
        finite = math.isfinite(self.mu_bar)
        return {"fs_hz": float(self.fs_hz), "delay_samples": int(self.delay_samples), "prewarp_rad_s": float(self.prewarp_rad_s),
                "implemented_mu_bar": float(self.mu_bar) if finite else None,
                "implemented_mu_bar_omega_rad_s": float(self.mu_bar_omega_rad_s) if finite else None,
                "nominally_stable": bool(self.nominally_stable), "image_ratio": float(self.image_ratio),
                "evaluated": "grid below Nyquist, refined at the peak (not band-certified)"}


def implemented_response(controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float, omega_rad_s) -> np.ndarray:
    """``K_impl(jw)`` of the module docstring at ``omega_rad_s`` (rad/s, physical units)."""
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    Ts = 1.0 / float(fs_hz)
    sos, gain = second_order_sections(controller, fs_hz, prewarp_rad_s)
    _, Kd = scipy.signal.sosfreqz(sos, worN=w * Ts)  # worN in rad/sample
    x = w * Ts
    hold = np.where(x > 0, (1.0 - np.exp(-1j * x)) / np.where(x > 0, 1j * x, 1.0), 1.0)
    return gain * Kd * np.exp(-1j * x * int(delay_samples)) * hold


def _closed_loop_response(plant: AugmentedPlant, omega: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``M(jw) = P_zw + P_zu K (1 - P_yu K)^-1 P_yw`` for a SISO ``K(jw)`` given by its values."""
    n = plant.A.shape[0]
    lhs = 1j * omega[:, None, None] * np.eye(n)[None] - plant.A[None]
    X = np.linalg.solve(lhs, np.broadcast_to(np.hstack([plant.Bw, plant.Bu]).astype(complex), (omega.size, n, plant.n_w + 1)))
    Pz = np.einsum("ij,wjk->wik", plant.Cz, X) + np.hstack([plant.Dzw, plant.Dzu])[None]
    Py = np.einsum("ij,wjk->wik", plant.Cy, X) + np.hstack([plant.Dyw, np.zeros((1, 1))])[None]
    Pzw, Pzu, Pyw, Pyu = Pz[:, :, :-1], Pz[:, :, -1:], Py[:, :, :-1], Py[:, 0, -1]
    factor = (K / (1.0 - Pyu * K))[:, None, None]
    return Pzw + factor * (Pzu @ Pyw)


def _sections_state_space(sos: np.ndarray, gain: float) -> tuple[np.ndarray, ...]:
    """The cascade of sections in direct form II transposed, as one discrete state space
    (two states per section: exactly the target's recursion, no polynomial)."""
    n = 2 * sos.shape[0]
    A, B, C, D = np.zeros((n, n)), np.zeros((n, 1)), np.zeros((1, n)), np.ones((1, 1))
    for i, (b0, b1, b2, _, a1, a2) in enumerate(sos):
        # the section's input is C x + D y of the cascade so far; its output out = b0 in + w0
        Ai = np.array([[-a1, 1.0], [-a2, 0.0]])
        Bi = np.array([[b1 - a1 * b0], [b2 - a2 * b0]])
        rows = slice(2 * i, 2 * i + 2)
        A[rows, :] = Bi @ C
        A[rows, rows] += Ai
        B[rows] = Bi @ D
        C = b0 * C
        C[0, 2 * i] += 1.0
        D = b0 * D
    return A, B, gain * C, gain * D


def _sampled_loop_stable(plant: AugmentedPlant, Ts: float, sos: np.ndarray, gain: float, delay: int) -> bool:
    """Eigenvalues of the sampled loop (nominal structure with its hold, the sections, the delay
    line) inside the unit circle."""
    n = plant.A.shape[0]
    Ad, Bd = held(plant.A, plant.Bu, Ts)
    Ak, Bk, Ck, Dk = _sections_state_space(sos, gain)
    nk = Ak.shape[0]
    size = n + nk + delay
    A = np.zeros((size, size))
    A[:n, :n] = Ad
    A[n:n + nk, :n] = Bk @ plant.Cy
    A[n:n + nk, n:n + nk] = Ak
    v_row = np.zeros((1, size))  # the compensator's output v[k] = Ck xi + Dk y
    v_row[:, :n], v_row[:, n:n + nk] = Dk @ plant.Cy, Ck
    if delay == 0:
        A[:n, :] += Bd @ v_row
    else:
        A[:n, n + nk + delay - 1] += Bd[:, 0]  # u[k] = the oldest register
        A[n + nk, :] = v_row  # the newest register takes v[k]
        for j in range(1, delay):
            A[n + nk + j, n + nk + j - 1] = 1.0
    return bool(np.max(np.abs(np.linalg.eigvals(A))) < 1.0)


def implemented_mu_bar(model: IntervalModel, weights: Weights, controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float,
                       gain: tuple[float, float] | None = None, omega_rad_s=None, performance: bool = True) -> ImplementedLoop:
    """mu-bar of the implemented loop (module docstring), in the analysis's normalised units
    (:func:`~setmem_hil.robust.analysis.analyze_robust_performance`'s notes), reported in rad/s.

    ``performance=False``: robust **stability** only (the parametric blocks and the unmodelled
    dynamics ``W1``, without the performance block ``W2``, the last complex block of eq. 6.20-6.22):
    what a loop engaged at a fraction of its gain must keep, since a smaller gain rejects less and
    cannot meet the performance it was designed for."""
    from setmem_hil.robust.analysis import default_grid_for

    T, M = weights.reference_frequency_rad_s(), weights.reference_magnitude()
    scaled = model.time_scaled(1.0 / T).magnitude_scaled(1.0 / M)
    plant = augmented_plant(uncertain_plant(scaled, gain), weights.time_scaled(1.0 / T).magnitude_scaled(1.0 / M), design_w2=True)
    nyquist = math.pi * fs_hz
    grid = default_grid_for(scaled) * T if omega_rad_s is None else np.sort(np.asarray(omega_rad_s, dtype=float))
    omega = grid[grid < NYQUIST_FRACTION * nyquist]
    sos, sos_gain = second_order_sections(controller, fs_hz, prewarp_rad_s)
    stable = _sampled_loop_stable(plant, T / fs_hz, sos, M * sos_gain, int(delay_samples))
    keep = plant.n_real + plant.n_complex - (0 if performance else 1)  # the performance block is the last
    structure = MuStructure(plant.n_real, plant.n_complex - (0 if performance else 1))

    def mu_at(w: np.ndarray) -> np.ndarray:
        K = M * implemented_response(controller, fs_hz, delay_samples, prewarp_rad_s, w)
        matrices = _closed_loop_response(plant, w / T, K)[:, :keep, :keep]
        return mixed_mu_upper(matrices, structure, tol=PRECISE_TOL, max_iter=PRECISE_MAX_ITER).beta

    mu = mu_at(omega)
    for _ in range(2):  # refine around the peak, as the continuous analysis does
        k = int(np.argmax(mu))
        lo, hi = omega[max(k - 1, 0)], omega[min(k + 1, omega.size - 1)]
        extra = np.linspace(lo, hi, 9)[1:-1]
        omega, mu = np.concatenate([omega, extra]), np.concatenate([mu, mu_at(extra)])
        order = np.argsort(omega)
        omega, mu = omega[order], mu[order]
    peak = int(np.argmax(mu))
    mu_bar = float(mu[peak]) if stable else math.inf
    deciding = omega[mu >= IMAGE_CHECK_LEVEL * mu[peak]]  # the frequencies that decide mu-bar
    return ImplementedLoop(float(fs_hz), int(delay_samples), float(prewarp_rad_s), mu_bar, float(omega[peak]), stable,
                           _image_ratio(plant, deciding / T, 2 * nyquist / T), omega, mu)


def _image_ratio(plant: AugmentedPlant, omega_n: np.ndarray, sampling_n: float) -> float:
    """max over the band of ``|G(j(ws - w))| / |G(jw)|`` through the nominal structure (u to y)."""
    def g(w):
        n = plant.A.shape[0]
        X = np.linalg.solve(1j * w[:, None, None] * np.eye(n)[None] - plant.A[None],
                            np.broadcast_to(plant.Bu.astype(complex), (w.size, n, 1)))
        return np.abs(np.einsum("ij,wjk->w", plant.Cy, X))

    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = g(sampling_n - omega_n) / g(omega_n)
    return float(np.nanmax(ratio)) if ratio.size else 0.0


def required_sample_rate(model: IntervalModel, weights: Weights, controller, delay_samples: int, prewarp_rad_s: float,
                         fs_hz: float, goal: float = 1.0, gain=None, max_factor: float = 64.0) -> float | None:
    """The lowest sample rate (doubling from ``fs_hz``, then bisection to 5 %) at which the
    implemented mu-bar is below ``goal``; None when even ``max_factor * fs_hz`` is not enough."""
    def ok(fs: float) -> bool:
        if prewarp_rad_s >= NYQUIST_FRACTION * math.pi * fs:
            return False
        return implemented_mu_bar(model, weights, controller, fs, delay_samples, prewarp_rad_s, gain).mu_bar < goal

    lo, hi = fs_hz, 2.0 * fs_hz
    while not ok(hi):
        lo, hi = hi, 2.0 * hi
        if hi > max_factor * fs_hz:
            return None
    while hi / lo > 1.05:
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi
