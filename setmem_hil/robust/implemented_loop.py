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
is visible. Nominal stability is checked exactly, on the sampled loop (the nominal structure
discretised with the hold, the sections, the delay line): an unstable one has mu-bar infinite.

**Two numbers.** ``mu_bar`` is the D,G-scaled bound of ``M`` with ``K_impl`` on a grid (the
analysis's default grid below Nyquist, refined twice around the peak): the closest figure to the
loop as it runs, but nothing is proved between grid points, since a delay has no finite state
space for the band certificate's Hamiltonian test. ``certified_mu_bar`` is a guarantee for the
whole band below :data:`NYQUIST_FRACTION` of Nyquist (ours; the thesis has no target): write
``K_impl = K (1 + delta)``; ``delta(w)`` is explicit, zero at DC (Tustin keeps the DC gain, the
hold and the delay are 1 there) and close to ``(D + 1/2) w Ts`` in magnitude (the delay and the
hold's half sample), larger near a compensator resonance that the Tustin map warps. A rational
weight ``W_delta(s) = g (D + 1/2) Ts s / (1 + (D + 1/2) Ts s / 2.2)`` covers it:
``|delta(w)| <= |W_delta(jw)|``, with ``g`` the smallest factor that makes it hold, plus
:data:`ENVELOPE_MARGIN`, on :data:`ENVELOPE_POINTS` frequencies (a scalar function of ``w``,
checked far more densely than the mu grid, four times denser up to three times while
``|delta| / |W_delta|`` changes by more than half the margin between neighbours: that largest
change is ``envelope_step``, and a certificate needs it below half the margin). Then ``delta`` becomes one more complex scalar
block, before the performance block (``u = K y + q``, ``q = delta_n p``, ``p = W_delta K y``), and
the continuous, rational loop is band-certified as the analysis certifies it
(:func:`~setmem_hil.robust.mu_certificate.certify_band`). If its level ``beta`` is below 1 the
implemented loop's mu-bar is below ``beta`` at every frequency of the band (the main loop
theorem: every ``|delta_n| <= 1 <= 1/beta`` is covered), so the guarantee is the certified level;
it is conservative by how much a complex ``delta`` of that size can do that the actual phase does
not. A level of 1 or more certifies nothing: a loop is engaged only on a level below 1.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.signal

from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import Weights
from setmem_hil.numerics.zero_order_hold import held
from setmem_hil.robust.augmented_plant import AugmentedPlant, StateSpaceMatrices, augmented_plant
from setmem_hil.robust.controller_forms import frequency_response, second_order_sections
from setmem_hil.robust.mixed_mu import MuStructure
from setmem_hil.robust.uncertain_plant import uncertain_plant

__all__ = ["ImplementedLoop", "implemented_response", "implemented_mu_bar", "required_sample_rate", "NYQUIST_FRACTION"]

NYQUIST_FRACTION = 0.95
"""The band evaluated ends here (a fraction of Nyquist): the hold's images meet the band at Nyquist."""
ENVELOPE_POINTS = 20_000
ENVELOPE_MARGIN = 0.05
"""``|W_delta| >= (1 + margin) |delta|`` at every one of the envelope's frequencies."""
CERTIFICATE_GRID_STRIDE = 3
"""The certificate starts from every third grid point's scalings (it solves more where they do not reach)."""
ENVELOPE_CEILING = 2.2
"""``|W_delta|`` at high frequency, over ``g``: ``|delta| <= |K_d / K| + 1``, about 2 where the sections follow ``K``."""
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
    certified_mu_bar: float = math.inf  # the band certificate's level with delta as a block (module docstring)
    certified: bool = False  # the certificate covered the whole band
    envelope_gain: float = math.nan  # g of W_delta
    envelope_step: float = math.nan  # the largest change of |delta| / |W_delta| between the envelope's neighbours

    @property
    def guaranteed_mu_bar(self) -> float:
        """What a decision may rely on: the certified level, infinite when nothing was certified."""
        return float(self.certified_mu_bar) if self.certified and self.nominally_stable else math.inf

    def to_document(self) -> dict:
        finite = math.isfinite(self.mu_bar)
        guaranteed = self.guaranteed_mu_bar
        return {"fs_hz": float(self.fs_hz), "delay_samples": int(self.delay_samples), "prewarp_rad_s": float(self.prewarp_rad_s),
                "implemented_mu_bar": float(self.mu_bar) if finite else None,
                "implemented_mu_bar_omega_rad_s": float(self.mu_bar_omega_rad_s) if finite else None,
                "implemented_mu_bar_certified": guaranteed if math.isfinite(guaranteed) else None,
                "nominally_stable": bool(self.nominally_stable), "image_ratio": float(self.image_ratio),
                "envelope_gain": float(self.envelope_gain), "envelope_step": float(self.envelope_step),
                "evaluated": "implemented_mu_bar: grid below 0.95 Nyquist, refined at the peak; implemented_mu_bar_certified: "
                             "band-certified below 0.95 Nyquist with the delay, hold and sections as a bounded complex "
                             "uncertainty on the compensator"}


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


_MEMO: "OrderedDict[tuple, ImplementedLoop]" = OrderedDict()
MEMO_SIZE = 64
"""The same loop asked again (a command's check, then the plan's step; a search over rates) is
answered from memory: the analysis is a pure function of its arguments."""


def _memo_key(model, weights, controller, *rest) -> tuple:
    arrays = (model.lower, model.upper, *(np.asarray(getattr(controller, name), dtype=float) for name in "ABCD"))
    return (tuple(a.tobytes() + str(a.shape).encode() for a in arrays), repr(weights),
            *(v.tobytes() if isinstance(v, np.ndarray) else v for v in rest))


def implemented_mu_bar(model: IntervalModel, weights: Weights, controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float,
                       gain: tuple[float, float] | None = None, omega_rad_s=None, performance: bool = True) -> ImplementedLoop:
    """mu-bar of the implemented loop (module docstring), in the analysis's normalised units
    (:func:`~setmem_hil.robust.analysis.analyze_robust_performance`'s notes), reported in rad/s.

    ``performance=False``: robust **stability** only (the parametric blocks and the unmodelled
    dynamics ``W1``, without the performance block ``W2``, the last complex block of eq. 6.20-6.22):
    what a loop engaged at a fraction of its gain must keep, since a smaller gain rejects less and
    cannot meet the performance it was designed for."""
    omega = None if omega_rad_s is None else np.sort(np.asarray(omega_rad_s, dtype=float))
    key = _memo_key(model, weights, controller, float(fs_hz), int(delay_samples), float(prewarp_rad_s),
                    None if gain is None else tuple(map(float, gain)), omega, bool(performance))
    if key in _MEMO:
        _MEMO.move_to_end(key)
        return _MEMO[key]
    loop = _implemented_mu_bar(model, weights, controller, fs_hz, delay_samples, prewarp_rad_s, gain, omega, performance)
    _MEMO[key] = loop
    while len(_MEMO) > MEMO_SIZE:
        _MEMO.popitem(last=False)
    return loop


def _implemented_mu_bar(model: IntervalModel, weights: Weights, controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float,
                        gain, omega_rad_s, performance: bool) -> ImplementedLoop:
    from setmem_hil.robust.analysis import default_grid_for, grid_bounds

    T, M = weights.reference_frequency_rad_s(), weights.reference_magnitude()
    scaled = model.time_scaled(1.0 / T).magnitude_scaled(1.0 / M)
    plant = augmented_plant(uncertain_plant(scaled, gain), weights.time_scaled(1.0 / T).magnitude_scaled(1.0 / M), design_w2=True)
    nyquist = math.pi * fs_hz
    grid = default_grid_for(scaled) * T if omega_rad_s is None else np.sort(np.asarray(omega_rad_s, dtype=float))
    omega = grid[grid < NYQUIST_FRACTION * nyquist]
    sos, sos_gain = second_order_sections(controller, fs_hz, prewarp_rad_s)
    stable = _sampled_loop_stable(plant, T / fs_hz, sos, M * sos_gain, int(delay_samples))
    keep, structure = _blocks_kept(plant, performance)

    class _Loop:  # the implemented loop's matrices at physical frequencies, for the analysis's grid passes
        @staticmethod
        def frequency_response(w: np.ndarray) -> np.ndarray:
            K = M * implemented_response(controller, fs_hz, delay_samples, prewarp_rad_s, w)
            return _closed_loop_response(plant, np.asarray(w, dtype=float) / T, K)[:, :keep, :keep]

    # as the continuous analysis: a fast pass, precise solves where the peak can be, refined twice
    omegas, _, bounds = grid_bounds(_Loop, structure, omega)
    omega, mu = np.concatenate(omegas), np.concatenate([b.beta for b in bounds])
    order = np.argsort(omega)
    omega, mu = omega[order], mu[order]
    peak = int(np.argmax(mu))
    mu_bar = float(mu[peak]) if stable else math.inf
    deciding = omega[mu >= IMAGE_CHECK_LEVEL * mu[peak]]  # the frequencies that decide mu-bar
    envelope = _lag_envelope(controller, fs_hz, delay_samples, prewarp_rad_s, float(omega[0]), NYQUIST_FRACTION * nyquist)
    certificate = _certified_with_lag_block(plant, controller, envelope, T, M, omega / T, performance) if stable else None
    return ImplementedLoop(float(fs_hz), int(delay_samples), float(prewarp_rad_s), mu_bar, float(omega[peak]), stable,
                           _image_ratio(plant, deciding / T, 2 * nyquist / T), omega, mu,
                           certified_mu_bar=math.inf if certificate is None else float(certificate.level),
                           certified=certificate is not None and bool(certificate.certified) and envelope.resolved,
                           envelope_gain=envelope.gain, envelope_step=envelope.step)


@dataclass(frozen=True)
class LagEnvelope:
    """``W_delta(s) = gain * tau s / (1 + tau s / ENVELOPE_CEILING)``, ``tau = (D + 1/2) Ts`` (module docstring)."""

    gain: float
    tau_s: float
    step: float  # the largest change of |delta| / |W_delta| between neighbouring frequencies

    @property
    def resolved(self) -> bool:
        return self.step < 0.5 * ENVELOPE_MARGIN

    def weight(self, frequency_unit_rad_s: float = 1.0) -> StateSpaceMatrices:
        """The weight's state space with frequencies in units of ``frequency_unit_rad_s`` (the
        analysis's normalised frequency: ``W_n(s_n) = W(s_n * unit)``)."""
        tau = self.tau_s * frequency_unit_rad_s
        pole = ENVELOPE_CEILING / tau
        # gain tau s / (1 + s / pole) = gain tau pole - gain tau pole^2 / (s + pole)
        return StateSpaceMatrices(np.array([[-pole]]), np.array([[1.0]]), np.array([[-self.gain * tau * pole ** 2]]),
                                  np.array([[self.gain * tau * pole]]))

    def magnitude(self, omega_rad_s: np.ndarray) -> np.ndarray:
        x = self.tau_s * np.asarray(omega_rad_s, dtype=float)
        return self.gain * x / np.sqrt(1.0 + (x / ENVELOPE_CEILING) ** 2)


def _lag_envelope(controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float, w_lo: float, w_hi: float) -> LagEnvelope:
    """The smallest ``g`` with ``|W_delta| >= (1 + margin) |delta|`` on the envelope's frequencies,
    made four times denser (up to three times) while ``|delta| / |W_delta|`` changes by more than
    half the margin between neighbours; ``step`` is that largest change (below half the margin, the
    ratio cannot reach 1 between two of them unless ``delta`` has a feature narrower than the spacing)."""
    unit = LagEnvelope(1.0, (int(delay_samples) + 0.5) / float(fs_hz), 0.0)
    for refinement in range(4):
        w = np.geomspace(max(w_lo, 1e-9 * w_hi), w_hi, ENVELOPE_POINTS * 4 ** refinement)
        continuous = frequency_response(controller, w)
        delta = implemented_response(controller, fs_hz, delay_samples, prewarp_rad_s, w) / continuous - 1.0
        ratio = np.abs(delta) / unit.magnitude(w)
        gain = (1.0 + ENVELOPE_MARGIN) * float(np.max(ratio))
        step = float(np.max(np.abs(np.diff(ratio)))) / gain  # in units of |delta| / |W_delta|
        if step < 0.5 * ENVELOPE_MARGIN:
            break
    return LagEnvelope(gain, unit.tau_s, step)


def _with_lag_block(plant: AugmentedPlant, weight: StateSpaceMatrices) -> AugmentedPlant:
    """``plant`` with one more complex block before the performance block: its input ``q`` adds
    to the drive the structure and ``W1`` see, its output is ``W_delta`` of the compensator's output."""
    n, nw = plant.A.shape[0], weight.A.shape[0]
    k = plant.n_real + plant.n_complex - 1  # the performance block's index
    Z = np.zeros
    A = np.block([[plant.A, Z((n, nw))], [Z((nw, n)), weight.A]])
    Bu = np.vstack([plant.Bu, weight.B])
    Bw = np.hstack([np.vstack([plant.Bw[:, :k], Z((nw, k))]), np.vstack([plant.Bu, Z((nw, 1))]),
                    np.vstack([plant.Bw[:, k:], Z((nw, plant.n_w - k))])])
    Cz = np.vstack([np.hstack([plant.Cz[:k], Z((k, nw))]), np.hstack([Z((1, n)), weight.C]),
                    np.hstack([plant.Cz[k:], Z((plant.Cz.shape[0] - k, nw))])])
    Dzw_old = np.hstack([plant.Dzw[:, :k], plant.Dzu, plant.Dzw[:, k:]])
    Dzw = np.vstack([Dzw_old[:k], Z((1, Dzw_old.shape[1])), Dzw_old[k:]])
    Dzu = np.vstack([plant.Dzu[:k], weight.D, plant.Dzu[k:]])
    Cy = np.hstack([plant.Cy, Z((1, nw))])
    Dyw = np.hstack([plant.Dyw[:, :k], Z((1, 1)), plant.Dyw[:, k:]])
    return AugmentedPlant(A, Bw, Bu, Cz, Dzw, Dzu, Cy, Dyw, plant.n_real, plant.n_complex + 1, plant.names)


def _certified_with_lag_block(plant: AugmentedPlant, controller, envelope: LagEnvelope, T: float, M: float, omega_n: np.ndarray,
                              performance: bool):
    """The band certificate of the loop with ``delta`` as a block, on the band of ``omega_n``
    (normalised); None when that loop is not stable (nothing certified)."""
    from setmem_hil.robust.analysis import certify_grid, grid_bounds, time_scaled_controller

    augmented = _with_lag_block(plant, envelope.weight(T))
    loop = augmented.closed_loop(time_scaled_controller(controller, 1.0 / T, M))
    if np.max(np.linalg.eigvals(loop.A).real) >= 0.0:
        return None
    keep, structure = _blocks_kept(augmented, performance)
    loop = StateSpaceMatrices(loop.A, loop.B[:, :keep], loop.C[:keep], loop.D[:keep, :keep])
    omegas, _, bounds = grid_bounds(loop, structure, np.asarray(omega_n, dtype=float)[::CERTIFICATE_GRID_STRIDE])
    return certify_grid(loop, structure, omegas, bounds)


def _blocks_kept(plant: AugmentedPlant, performance: bool) -> tuple[int, MuStructure]:
    """How many of the loop's channels the analysis keeps, and their structure: all, or all but the
    performance block (the last) for robust stability alone."""
    dropped = 0 if performance else 1
    return plant.n_real + plant.n_complex - dropped, MuStructure(plant.n_real, plant.n_complex - dropped)


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
    certified implemented mu-bar is below ``goal``; None when no rate up to ``max_factor * fs_hz``
    is enough.

    The highest rate is asked first: when even its *estimate* (the grid's mu-bar, never above the
    certified level) is not below ``goal``, no rate is (the search takes the loop to improve with
    the rate), and a loop whose continuous margin is already thin (the refusals' usual case) costs
    one analysis instead of six. Its *certificate* is not relied on the same way: a band up to
    0.95 Nyquist at a high rate is long, and the certificate's budget of Hamiltonian tests can run
    out there while a lower rate is certified (the demo's loop at 2,560 Hz, stop 67); then the
    rates are doubled from ``fs_hz`` as if the top were unknown."""
    def analysed(fs: float) -> ImplementedLoop | None:
        if prewarp_rad_s >= NYQUIST_FRACTION * math.pi * fs:
            return None
        return implemented_mu_bar(model, weights, controller, fs, delay_samples, prewarp_rad_s, gain)

    def ok(fs: float) -> bool:
        loop = analysed(fs)
        return loop is not None and loop.guaranteed_mu_bar < goal

    top = max_factor * fs_hz
    at_top = analysed(top)
    if at_top is None or not at_top.mu_bar < goal:
        return None
    top_holds = at_top.guaranteed_mu_bar < goal
    lo, hi = fs_hz, 2.0 * fs_hz
    while not ok(hi):
        lo, hi = hi, 2.0 * hi
        if hi >= top:
            if not top_holds:
                return None
            hi = top
            break
    while hi / lo > 1.05:
        mid = math.sqrt(lo * hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return hi
