"""Bernoulli-Euler cantilever beam: tip force to tip displacement (thesis section 6.1).

Natural frequencies come from the cantilever frequency equation ``cos(x) cosh(x) = -1``
(roots ``x_k``, ``omega_k proportional to x_k^2``), normalised so the first mode is at 1 rad/s.
Every mode has damping ratio 0.01 and residue ``b0 = 4``, ``b1 = 0`` (displacement sensor).
The thesis truncates to the first 8 modes (16 states) and identifies the first three; the
other five are unmodelled dynamics, bounded by ``W1`` of eq. (6.1).
"""

from __future__ import annotations

import numpy as np

from setmem_hil.model.modal_model import ModalParameters

BEAM_DAMPING_RATIO = 0.01
BEAM_RESIDUE = 4.0
BEAM_N_MODES = 8

# W1(s) = 0.182 (s^2 + 15.2 s + 361)^2 / (s^2 + 26.4 s + 1089)^2   (eq. 6.1)
W1_NUM = tuple(0.182 * np.polymul([1.0, 15.2, 361.0], [1.0, 15.2, 361.0]))
W1_DEN = tuple(np.polymul([1.0, 26.4, 1089.0], [1.0, 26.4, 1089.0]))

# A priori natural-frequency bounds of the first three modes (section 6.1), zeta <= 0.5.
PRIOR_OMEGA_BOUNDS = ((0.884, 1.125), (5.41, 7.34), (16.35, 19.81))
PRIOR_ZETA_MAX = 0.5


def cantilever_eigenvalues(n_modes: int) -> np.ndarray:
    """First ``n_modes`` positive roots of ``cos(x) cosh(x) = -1``.

    Root k lies in ``((k - 1) pi, k pi)`` (cos changes sign once there, near ``(k - 1/2) pi``);
    the equation is written as
    ``cos(x) + 1/cosh(x) = 0`` so it stays well scaled for large x.
    """
    from scipy.optimize import brentq  # here: importing scipy.optimize costs a second (fast --help, run --check)

    f = lambda x: np.cos(x) + 1.0 / np.cosh(x)  # noqa: E731
    return np.array([brentq(f, (k - 1) * np.pi, k * np.pi, xtol=1e-15) for k in range(1, n_modes + 1)])


def beam_natural_frequencies(n_modes: int = BEAM_N_MODES) -> np.ndarray:
    """Natural frequencies (rad/s), first mode normalised to 1: ``(x_k / x_1)^2``."""
    x = cantilever_eigenvalues(n_modes)
    return (x / x[0]) ** 2


def beam_parameters(n_modes: int = BEAM_N_MODES) -> ModalParameters:
    """True parameters of the simulated beam (``a0 = 1, 39.274, 307.91, ...``)."""
    return ModalParameters.from_modal(beam_natural_frequencies(n_modes), BEAM_DAMPING_RATIO, BEAM_RESIDUE, 0.0)


def cantilever_mode_shape(x_k: float, position) -> np.ndarray:
    """Mass-normalised mode shape of a uniform cantilever (unit length and mass) at ``position``
    (fraction of the length from the clamp): ``cosh - cos - sigma (sinh - sin)`` of ``x_k xi``,
    ``sigma = (cosh x_k + cos x_k) / (sinh x_k + sin x_k)``; its tip value is +-2.

    Written with ``exp(-x xi)`` so it stays accurate for high modes, where ``cosh`` and
    ``sigma sinh`` cancel to many digits."""
    xi = np.asarray(position, dtype=float)
    z = x_k * xi
    denominator = np.sinh(x_k) + np.sin(x_k)
    sigma = (np.cosh(x_k) + np.cos(x_k)) / denominator
    # cosh z - sigma sinh z = ((1 - sigma) e^z + (1 + sigma) e^-z) / 2, with 1 - sigma (about
    # 2 e^-2x_k) formed without the cancellation: (sin x - cos x - e^-x) / (sinh x + sin x)
    one_minus_sigma = (np.sin(x_k) - np.cos(x_k) - np.exp(-x_k)) / denominator
    return 0.5 * (one_minus_sigma * np.exp(z) + (1.0 + sigma) * np.exp(-z)) - np.cos(z) + sigma * np.sin(z)


def scaled_beam(params: ModalParameters, first_mode_rad_s: float) -> ModalParameters:
    """``params`` (the beam at 1 rad/s) with every frequency times ``S = first_mode_rad_s``:
    ``a1, b1`` times S, ``a0, b0`` times S^2, so ``G_S(j w) = G(j w / S)`` (issue 18's rule)."""
    S = float(first_mode_rad_s)
    return params if S == 1.0 else ModalParameters(params.values * np.array([S, S * S, S, S * S]))


def beam_parameters_at(sensor: float, actuator: float = 1.0, n_modes: int = BEAM_N_MODES) -> ModalParameters:
    """The simulated beam seen from a force at ``actuator`` and a displacement sensor at
    ``sensor`` (fractions of the length from the clamp; issue 25). Same poles as
    :func:`beam_parameters`; residues ``b0_i = phi_i(actuator) phi_i(sensor)`` (unit modal
    mass), which is the thesis's ``b0 = 4`` at the tip for both."""
    for name, value in (("sensor", sensor), ("actuator", actuator)):
        if not 0.0 < float(value) <= 1.0:
            raise ValueError(f"{name}: expected a position in (0, 1] (fraction of the length from the clamp), found {value!r}")
    x = cantilever_eigenvalues(n_modes)
    b0 = np.array([cantilever_mode_shape(xk, actuator) * cantilever_mode_shape(xk, sensor) for xk in x])
    return ModalParameters.from_modal(beam_natural_frequencies(n_modes), BEAM_DAMPING_RATIO, b0, 0.0)


def polynomial_magnitude(num, den, omega_rad_s) -> np.ndarray:
    """``|num(j omega) / den(j omega)|`` for coefficient lists (highest power first)."""
    s = 1j * np.asarray(omega_rad_s, dtype=float)
    return np.abs(np.polyval(num, s) / np.polyval(den, s))


def w1_magnitude(omega_rad_s, num=W1_NUM, den=W1_DEN) -> np.ndarray:
    """``|W1(j omega)|``, the additive unmodelled-dynamics bound of eq. (6.1)."""
    return polynomial_magnitude(num, den, omega_rad_s)


def fully_damped_magnitude(params: ModalParameters, omega_rad_s) -> np.ndarray:
    """``|G(j omega)|`` with every pole and zero moved to damping 1 (section 6.2 noise shape).

    Each root ``r`` of the numerator and denominator of ``G`` is replaced by ``-|r|``: a complex
    pair of natural frequency ``w_n`` becomes ``(s + w_n)^2`` (damping 1) and the DC gain is
    unchanged. This is the thesis's recipe for a noise bound with a similar signal-to-noise
    ratio at every mode.
    """
    A, B, C, _ = params.state_space_matrices()
    den = np.poly(np.linalg.eigvals(A))
    # numerator of sum_i (b1 s + b0) / d_i(s): sum_i (b1 s + b0) prod_{k != i} d_k(s)
    num = np.zeros(1)
    for i, (a1, a0, b1, b0) in enumerate(params.values):
        term = np.array([b1, b0])
        for k, (c1, c0, _, _) in enumerate(params.values):
            if k != i:
                term = np.polymul(term, [1.0, c1, c0])
        num = np.polyadd(num, term)
    num = np.trim_zeros(num, "f")
    gain = num[0] / den[0]
    zeros = np.roots(num)
    poles = np.roots(den)
    s = 1j * np.asarray(omega_rad_s, dtype=float)[..., None]
    mag = np.abs(gain) * np.prod(np.abs(s + np.abs(zeros)), axis=-1) / np.prod(np.abs(s + np.abs(poles)), axis=-1)
    return mag
