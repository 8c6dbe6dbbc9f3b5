"""Beam data with a hidden effect the three-mode model lacks (test data for issue 6).

The truth is the first three modes of the simulated cantilever (:func:`beam_parameters`,
``truncated(3)``; the prior of :func:`setmem_hil.io.procedure.thesis_beam_prior` knows exactly
these three modes) combined with one hidden effect, plus bounded complex noise (eq. 3.7):

``none``
    Clean data: ``g = G3 + n``.
``time_delay``
    ``g = G3 e^{-j omega tau} + n``; ``tau`` such that the phase lag at the top of the band,
    ``omega_top tau``, is log-uniform in 5-60 degrees.
``first_order_lag``
    ``g = G3 / (j omega tau + 1) + n``; corner ``1 / tau`` log-uniform in 3-40 rad/s (inside the
    band).
``feedthrough``
    ``g = G3 + d + n``; ``|d|`` log-uniform in 1-10 times the noise bound at the top of the band
    (where the three-mode response is smallest), random sign.
``extra_mode``
    ``g = G3 + (b0 / (s^2 + 2 zeta w s + w^2)) + n``: natural frequency ``w`` log-uniform in one of
    the gaps between the prior's frequency bands, 10% clear of them
    (1.24-4.92, 8.07-14.86, 21.8-36 rad/s), ``zeta`` log-uniform in 0.005-0.05 and the peak
    ``|b0| / (2 zeta w^2)`` log-uniform in 3-30 times the noise bound at ``w``, random sign.

Noise bound: ``R = c * fully_damped(G3)`` (section 6.2's shape) with ``c`` log-uniform in
0.05-0.2; noise uniform in magnitude and phase below ``R``.

Frequency grid: 60 points log-spaced over 0.3-40 rad/s plus 6 points at ratios
0.98, 0.99, 0.995, 1.005, 1.01, 1.02 of each true natural frequency (78 points).

Detectability and distinguishability (documented exclusion rule): a hidden effect is only a
fair question if neither the three-mode structure nor another candidate with no more added
parameters can absorb it (e.g. a delay of a few degrees is, within the bound, also a first-order
lag with its corner far above the band). For each draw we fit those competitors (within the
prior) to the *noise-free* effect-laden response and take the smallest worst normalised residual
``m`` (bounds as above). Because ``|n| <= R``, a competitor's best residual on the noisy data is
at least ``m - 1``; draws with ``m < DETECTABLE_MARGIN`` (2.0) are redrawn, so the effect stands
out above the bound whatever the noise. The redraw count is recorded.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from setmem_hil.discrepancy.effect_models import EFFECT_MODELS, ExtraMode
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import PRIOR_OMEGA_BOUNDS, PRIOR_ZETA_MAX, beam_parameters, fully_damped_magnitude
from setmem_hil.sim_backends.noise import bounded_complex_noise

HIDDEN_EFFECTS: tuple[str, ...] = ("none", "time_delay", "first_order_lag", "feedthrough", "extra_mode")
DETECTABLE_MARGIN = 2.0
OMEGA_BAND_RAD_S = (0.3, 40.0)
NOISE_SCALE_RANGE = (0.05, 0.2)
DELAY_PHASE_DEG_RANGE = (5.0, 60.0)
LAG_CORNER_RAD_S_RANGE = (3.0, 40.0)
FEEDTHROUGH_BOUND_RATIO_RANGE = (1.0, 10.0)
EXTRA_MODE_GAPS_RAD_S = ((1.24, 4.92), (8.07, 14.86), (21.8, 36.0))
EXTRA_MODE_ZETA_RANGE = (0.005, 0.05)
EXTRA_MODE_PEAK_BOUND_RATIO_RANGE = (3.0, 30.0)
MAX_REDRAWS = 50


@dataclass(frozen=True)
class HiddenEffectCase:
    """One generated data set.

    Attributes
    ----------
    effect : str
        The hidden effect (``"none"`` for clean data).
    params : dict
        Its true parameters (``tau`` s, ``d``, or ``omega_n``, ``zeta``, ``b0``, ``b1``).
    data : FrequencyData
        Noisy response with the noise bound.
    truth : ModalParameters
        The three modelled modes.
    noise_scale : float
        ``c`` in ``R = c * fully_damped``.
    margin : float
        ``m``: the best competitor's worst normalised residual on the noise-free response (0 for
        clean data).
    redraws : int
        Strength draws rejected by the detectability rule.
    """

    effect: str
    params: dict = field(default_factory=dict)
    data: FrequencyData | None = None
    truth: ModalParameters | None = None
    noise_scale: float = 0.0
    margin: float = 0.0
    redraws: int = 0


def hidden_effect_omegas(truth: ModalParameters | None = None) -> np.ndarray:
    """The 78-point grid: 60 log-spaced over 0.3-40 rad/s plus 6 around each true peak."""
    truth = beam_parameters().truncated(3) if truth is None else truth
    ratios = np.array([0.98, 0.99, 0.995, 1.005, 1.01, 1.02])
    near = (truth.natural_frequencies[:, None] * ratios[None, :]).ravel()
    return np.sort(np.concatenate([np.geomspace(*OMEGA_BAND_RAD_S, 60), near]))


def apply_effect(effect: str, params: dict, g_modal: np.ndarray, omega_rad_s: np.ndarray) -> np.ndarray:
    """The effect-laden response from the three-mode response ``g_modal``."""
    s = 1j * np.asarray(omega_rad_s, dtype=float)
    if effect == "none":
        return g_modal.copy()
    if effect in EFFECT_MODELS:
        model = EFFECT_MODELS[effect]
        return model.apply(g_modal, s, params[model.param_names[0]])
    if effect == ExtraMode.name:
        return ExtraMode.apply(g_modal, s, params["omega_n"], params["zeta"], params["b0"], params["b1"])
    raise ValueError(f"effect: expected one of {HIDDEN_EFFECTS}, found {effect!r}")


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _draw_params(effect: str, rng: np.random.Generator, omega: np.ndarray, bound_fn) -> dict:
    top = float(omega.max())
    if effect == "time_delay":
        return {"tau": np.deg2rad(_log_uniform(rng, *DELAY_PHASE_DEG_RANGE)) / top}
    if effect == "first_order_lag":
        return {"tau": 1.0 / _log_uniform(rng, *LAG_CORNER_RAD_S_RANGE)}
    if effect == "feedthrough":
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        return {"d": sign * _log_uniform(rng, *FEEDTHROUGH_BOUND_RATIO_RANGE) * float(bound_fn(np.array([top]))[0])}
    if effect == "extra_mode":
        gap = EXTRA_MODE_GAPS_RAD_S[int(rng.integers(len(EXTRA_MODE_GAPS_RAD_S)))]
        w = _log_uniform(rng, *gap)
        z = _log_uniform(rng, *EXTRA_MODE_ZETA_RANGE)
        peak = _log_uniform(rng, *EXTRA_MODE_PEAK_BOUND_RATIO_RANGE) * float(bound_fn(np.array([w]))[0])
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        return {"omega_n": w, "zeta": z, "b0": sign * peak * 2 * z * w * w, "b1": 0.0}
    return {}


def competitor_margin(effect: str, truth: ModalParameters, response: np.ndarray, omega: np.ndarray, bound: np.ndarray,
                      stop_below: float = DETECTABLE_MARGIN) -> float:
    """Smallest best worst normalised residual of the competitors of ``effect`` on ``response``.

    Competitors are the structures with no more added parameters (:func:`_competitors`), fitted
    within the prior by the candidate library of :mod:`setmem_hil.discrepancy.effects`, started at
    the true modes (without the final SLSQP polish: a fit that stops short overstates the margin,
    i.e. admits a harder case). A first-order lag whose fitted corner lies above the band is, in
    the band, a delay (the workflow names it ``time_delay``), so it is no competitor of a delay.
    Stops early once a margin falls below ``stop_below``.
    """
    from setmem_hil.discrepancy.effects import ModalBox, fit_candidate, fit_none

    lo = np.array([[0.0, a**2, 0.0, -np.inf] for a, _ in PRIOR_OMEGA_BOUNDS])
    hi = np.array([[2 * PRIOR_ZETA_MAX * b, b**2, 0.0, np.inf] for _, b in PRIOR_OMEGA_BOUNDS])
    data = FrequencyData(omega, response, bound)
    box = ModalBox(lo, hi, truth.values)
    none = fit_none(data, box, polish=False)
    margin = none.max_normalized_residual
    for name in _competitors(effect)[1:]:
        if margin < stop_below:
            break
        fit = fit_candidate(name, data, box, none, polish=False)
        if name == "first_order_lag" and effect == "time_delay":
            tau = fit.params["tau"]
            if tau <= 0 or 1.0 / tau > float(np.max(omega)):
                continue
        margin = min(margin, fit.max_normalized_residual)
    return margin


def _competitors(effect: str) -> tuple[str, ...]:
    """Structures with no more added parameters than ``effect`` (they would be named first)."""
    one = ("time_delay", "first_order_lag", "feedthrough")
    if effect == "extra_mode":
        return ("none",) + one
    return ("none",) + tuple(e for e in one if e != effect)


def draw_hidden_effect_case(effect: str, seed: int, noise_scale: float | None = None,
                            detectable_margin: float = DETECTABLE_MARGIN) -> HiddenEffectCase:
    """Generate one case with ``effect`` hidden (random strength and noise from ``seed``).

    Parameters
    ----------
    effect : str
        One of :data:`HIDDEN_EFFECTS`.
    seed : int
        Seeds ``numpy.random.default_rng``; the same seed gives the same case.
    noise_scale : float, optional
        Fix ``c``; default drawn log-uniform in :data:`NOISE_SCALE_RANGE`.
    detectable_margin : float
        Redraw strengths whose competitor margin is below this (default
        :data:`DETECTABLE_MARGIN`; lower values admit harder, possibly ambiguous cases).

    Returns
    -------
    HiddenEffectCase
    """
    if effect not in HIDDEN_EFFECTS:
        raise ValueError(f"effect: expected one of {HIDDEN_EFFECTS}, found {effect!r}")
    rng = np.random.default_rng(seed)
    truth = beam_parameters().truncated(3)
    omega = hidden_effect_omegas(truth)
    c = _log_uniform(rng, *NOISE_SCALE_RANGE) if noise_scale is None else float(noise_scale)

    def bound_fn(w):
        return c * fully_damped_magnitude(truth, w)

    bound = bound_fn(omega)
    g_modal = truth.frequency_response(omega)
    params: dict = {}
    margin = 0.0
    redraws = 0
    if effect != "none":
        for redraws in range(MAX_REDRAWS):
            params = _draw_params(effect, rng, omega, bound_fn)
            margin = competitor_margin(effect, truth, apply_effect(effect, params, g_modal, omega), omega, bound)
            if margin >= detectable_margin:
                break
        else:  # pragma: no cover - the ranges above make this practically impossible
            raise RuntimeError(f"{effect}: no detectable strength in {MAX_REDRAWS} draws (seed {seed})")
    g = apply_effect(effect, params, g_modal, omega) + bounded_complex_noise(bound, rng)
    return HiddenEffectCase(effect, {k: float(v) for k, v in params.items()}, FrequencyData(omega, g, bound), truth, c, margin, redraws)
