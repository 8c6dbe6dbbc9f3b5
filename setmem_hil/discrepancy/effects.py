"""Library of candidate effects a modal model may lack, and their fits to data.

Each candidate is a parametric augmentation of the modal model ``G`` of eq. (3.6):

``none`` (0 added parameters)
    ``G`` itself: the data agree with the model within the bound.
``time_delay`` (1: ``tau`` s)
    ``G(s) e^{-s tau}``: acquisition latency.
``first_order_lag`` (1: ``tau`` s)
    ``G(s) / (tau s + 1)``: sensor or actuator bandwidth.
``feedthrough`` (1: ``d``)
    ``G(s) + d``: residual flexibility of modes above the band.
``extra_mode`` (3: ``a1, a0, b0``; 4 when ``b1`` is free in the prior)
    ``G(s) + (b1 s + b0) / (s^2 + a1 s + a0)``: an unmodelled mode inside the measured band,
    with the same ``b1`` rule as the modelled modes.

Every candidate is fitted jointly with the modal parameters (kept inside the prior's box) by
:func:`setmem_hil.discrepancy.fit.fit_minimax`, which minimises the worst normalised residual
``max_i |g_i - G_i| / R_i`` (eq. 3.8 divided by its bound). Starts: the ``none`` fit for the
modal part; a few values of each effect parameter (multi-start, the best least-squares fit is
refined to minimax).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.discrepancy.fit import EFFECT_PARAM_NAMES, fit_minimax, model_response
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters

CANDIDATE_EFFECTS: tuple[str, ...] = ("none", "time_delay", "first_order_lag", "feedthrough", "residual_mass", "extra_mode")
DELAY_START_PHASE_DEG = (3.0, 15.0, 60.0)
LAG_START_CORNER_RATIOS = (3.0, 1.0, 1.0 / 3.0, 0.1)
EXTRA_MODE_START_ZETAS = (0.003, 0.01, 0.03, 0.1)
ZETA_FLOOR = 1e-4
EXTRA_MODE_N_STARTS = 3
EXTRA_MODE_GRID_POINTS = 240


@dataclass(frozen=True)
class ModalBox:
    """Box of modal parameters ``lower <= (a1, a0, b1, b0) <= upper`` (shape (n, 4)) and a start."""

    lower: np.ndarray
    upper: np.ndarray
    start: np.ndarray

    def __post_init__(self):
        lo = np.array(self.lower, dtype=float).reshape(-1, 4)
        # damping floor: a1 = 0 puts a pole on the imaginary axis (infinite response at a data
        # point that hits omega_n exactly)
        lo[:, 0] = np.maximum(lo[:, 0], 2 * ZETA_FLOOR * np.sqrt(np.maximum(lo[:, 1], 0.0)))
        hi = np.maximum(np.array(self.upper, dtype=float).reshape(-1, 4), lo)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "start", np.clip(np.array(self.start, dtype=float).reshape(-1, 4), lo, hi))

    @property
    def n_modes(self) -> int:
        return int(np.asarray(self.lower).shape[0])

    def b1_rule(self) -> tuple[float, float]:
        """``(b1_min, b1_max)`` for an added mode: the common fixed ``b1`` if every mode fixes the
        same value (``b1 = 0`` for a displacement sensor), else unbounded."""
        lo = np.asarray(self.lower)[:, 2]
        hi = np.asarray(self.upper)[:, 2]
        if np.all(lo == hi) and np.all(lo == lo[0]):
            return float(lo[0]), float(lo[0])
        return -np.inf, np.inf

    def zeta_max(self) -> float:
        """Largest damping ratio the box allows (``a1_max / (2 sqrt(a0_min))``)."""
        lo = np.asarray(self.lower)
        hi = np.asarray(self.upper)
        return float(np.max(hi[:, 0] / (2.0 * np.sqrt(np.maximum(lo[:, 1], 1e-300)))))


@dataclass(frozen=True)
class CandidateFit:
    """The best fit of one candidate structure.

    Attributes
    ----------
    name : str
        Candidate name (:data:`CANDIDATE_EFFECTS`).
    n_added_params : int
        Parameters the effect adds to the modal model.
    max_normalized_residual : float
        Worst ``|g - G| / R`` at the fit (<= 1: the structure is consistent with the data).
    normalized_residual : ndarray
        Per data point.
    theta : ndarray
        Fitted parameters (modal values flattened, then the effect's).
    n_modes : int
        Modes of the base model.
    params : dict
        The effect's parameters by name (``tau``, ``d``; ``omega_n``, ``zeta``, ``b0``, ``b1`` for
        an extra mode).
    """

    name: str
    n_added_params: int
    max_normalized_residual: float
    normalized_residual: np.ndarray
    theta: np.ndarray
    n_modes: int
    params: dict

    @property
    def modal(self) -> ModalParameters:
        """The fitted base modes (without the effect)."""
        return ModalParameters(self.theta[: 4 * self.n_modes].reshape(-1, 4))

    def response(self, omega_rad_s) -> np.ndarray:
        """``G`` of the augmented structure at the fit."""
        return model_response(self.name, self.theta, self.n_modes, np.atleast_1d(np.asarray(omega_rad_s, dtype=float)))[0]


def _effect_params(name: str, theta_effect: np.ndarray) -> dict:
    if name == "extra_mode":
        a1, a0, b1, b0 = (float(v) for v in theta_effect)
        wn = float(np.sqrt(max(a0, 0.0)))
        return {"omega_n": wn, "zeta": a1 / (2 * wn) if wn > 0 else 0.0, "b0": b0, "b1": b1}
    return {k: float(v) for k, v in zip(EFFECT_PARAM_NAMES[name], theta_effect)}


def _candidate(name: str, fit, n_modes: int, n_added: int) -> CandidateFit:
    theta = fit.theta
    return CandidateFit(
        name, n_added, fit.max_normalized_residual, fit.normalized_residual, theta, n_modes,
        _effect_params(name, theta[4 * n_modes:]),
    )


def initial_modal_estimate(data: FrequencyData, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Start values ``(n, 4)`` from the data and a prior box (peak picking plus linear residues).

    For each mode the natural frequency is the data frequency of largest ``|g|`` inside the
    mode's prior band (its geometric centre if no data fall there). Over a few common damping
    ratios the residues are then linear (eq. 3.6 with the poles fixed): a weighted least-squares
    solve (weights ``1 / R``); the damping with the smallest weighted error is kept.
    """
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    w = data.omega_rad_s
    g = data.response
    weight = 1.0 / np.maximum(data.bound, 1e-12 * np.max(np.abs(g)))
    n = lo.shape[0]
    wn = np.empty(n)
    for i in range(n):
        band = (w**2 >= lo[i, 1]) & (w**2 <= hi[i, 1])
        wn[i] = w[band][np.argmax(np.abs(g[band]))] if np.any(band) else np.sqrt(np.sqrt(lo[i, 1] * hi[i, 1]))
    b1_fixed = lo[:, 2] == hi[:, 2]
    best = None
    s = 1j * w
    for zeta in (0.002, 0.005, 0.01, 0.02, 0.05, 0.1):
        a1 = np.clip(2 * zeta * wn, lo[:, 0], hi[:, 0])
        a0 = wn**2
        den = s[None, :] ** 2 + a1[:, None] * s[None, :] + a0[:, None]
        cols = []
        target = g - sum((lo[i, 2] * s / den[i] for i in range(n) if b1_fixed[i]), np.zeros_like(g))
        for i in range(n):
            cols.append(1.0 / den[i])
            if not b1_fixed[i]:
                cols.append(s / den[i])
        A = np.column_stack(cols) * weight[:, None]
        Ar = np.vstack([A.real, A.imag])
        br = np.concatenate([(target * weight).real, (target * weight).imag])
        coef, *_ = np.linalg.lstsq(Ar, br, rcond=None)
        err = float(np.max(np.abs(Ar @ coef - br)))
        if best is None or err < best[0]:
            vals = np.column_stack([a1, a0, lo[:, 2], np.zeros(n)])
            k = 0
            for i in range(n):
                vals[i, 3] = coef[k]
                k += 1
                if not b1_fixed[i]:
                    vals[i, 2] = coef[k]
                    k += 1
            best = (err, vals)
    vals = best[1]
    return np.clip(vals, lo, hi)


def fit_none(data: FrequencyData, box: ModalBox, polish: bool = True, robust: bool = False) -> CandidateFit:
    """Best fit of the modal structure alone inside ``box``.

    ``robust``: instead of the minimax fit, a robust least-squares fit (soft-L1 loss on the
    normalised residuals) that keeps a localised discrepancy in place (for "where").
    """
    n = box.n_modes
    fit = fit_minimax("none", n, np.asarray(box.start).ravel(), np.asarray(box.lower).ravel(),
                      np.asarray(box.upper).ravel(), data.omega_rad_s, data.response, data.bound, polish=polish,
                      minimax=not robust, loss="soft_l1" if robust else "linear")
    return _candidate("none", fit, n, 0)


def _best_of_starts(name, data, box, modal0, starts, lo_e, hi_e, scale_e, polish=True) -> CandidateFit:
    n = box.n_modes
    lo = np.concatenate([np.asarray(box.lower).ravel(), lo_e])
    hi = np.concatenate([np.asarray(box.upper).ravel(), hi_e])
    scale = np.concatenate([np.where(np.abs(modal0) > 0, np.abs(modal0), 1.0), scale_e])
    args = (data.omega_rad_s, data.response, data.bound)
    screened = []
    for start in starts:
        th0 = np.concatenate([modal0, np.asarray(start, dtype=float)])
        screened.append(fit_minimax(name, n, th0, lo, hi, *args, scale=scale, minimax=False))
    best = min(screened, key=lambda f: f.max_normalized_residual)
    final = fit_minimax(name, n, best.theta, lo, hi, *args, scale=scale, polish=polish)
    if final.max_normalized_residual > best.max_normalized_residual:
        final = best
    n_added = int(np.sum(hi[4 * n:] > lo[4 * n:]))
    return _candidate(name, final, n, n_added)


def fit_time_delay(data: FrequencyData, box: ModalBox, modal0: np.ndarray, polish: bool = True,
                   tau_starts: tuple[float, ...] = ()) -> CandidateFit:
    """``G e^{-s tau}``, ``tau >= 0``; starts: phase lags of 3, 15, 60 degrees at the top frequency
    (plus ``tau_starts``)."""
    top = float(data.omega_rad_s.max())
    starts = [[np.deg2rad(p) / top] for p in DELAY_START_PHASE_DEG] + [[float(t)] for t in tau_starts]
    return _best_of_starts("time_delay", data, box, modal0, starts, np.array([0.0]), np.array([np.pi / top]), np.array([1.0 / top]), polish)


def fit_first_order_lag(data: FrequencyData, box: ModalBox, modal0: np.ndarray, polish: bool = True) -> CandidateFit:
    """``G / (tau s + 1)``, ``tau >= 0``; starts: corners at 3, 1, 1/3, 1/10 of the top frequency."""
    top = float(data.omega_rad_s.max())
    starts = [[1.0 / (r * top)] for r in LAG_START_CORNER_RATIOS]
    low = float(data.omega_rad_s.min())
    return _best_of_starts("first_order_lag", data, box, modal0, starts, np.array([0.0]), np.array([10.0 / low]), np.array([1.0 / top]), polish)


def fit_feedthrough(data: FrequencyData, box: ModalBox, modal0: np.ndarray, residual: np.ndarray, polish: bool = True) -> CandidateFit:
    """``G + d`` (``d`` real); starts: 0 and the weighted mean of the ``none`` residual."""
    wgt = 1.0 / np.maximum(data.bound, 1e-300) ** 2
    d0 = float(np.sum(wgt * residual.real) / np.sum(wgt))
    typical = float(np.median(data.bound))
    return _best_of_starts("feedthrough", data, box, modal0, [[0.0], [d0]], np.array([-np.inf]), np.array([np.inf]), np.array([typical]), polish)


def fit_residual_mass(data: FrequencyData, box: ModalBox, modal0: np.ndarray, residual: np.ndarray, polish: bool = True) -> CandidateFit:
    """``G + r / s^2`` (``r`` real); starts: 0 and the weighted least-squares ``r`` of the ``none`` residual."""
    phi = -1.0 / data.omega_rad_s**2
    wgt = 1.0 / np.maximum(data.bound, 1e-300) ** 2
    r0 = float(np.sum(wgt * phi * residual.real) / np.sum(wgt * phi * phi))
    typical = float(np.median(data.bound * data.omega_rad_s**2))
    return _best_of_starts("residual_mass", data, box, modal0, [[0.0], [r0]], np.array([-np.inf]), np.array([np.inf]), np.array([typical]), polish)


def extra_mode_starts(data: FrequencyData, residual: np.ndarray, b1: float, n_starts: int = EXTRA_MODE_N_STARTS) -> list:
    """Starts ``(a1, a0, b1, b0)`` for an added mode: a grid search on the residual.

    Over :data:`EXTRA_MODE_GRID_POINTS` log-spaced natural frequencies across the measured band
    and the damping ratios :data:`EXTRA_MODE_START_ZETAS`, the residue ``b0`` of a mode fitted
    to the residual is linear (weighted least squares, weights ``1 / R``); the score is the
    remaining sum of squared normalised residuals. The ``n_starts`` best grid points at distinct
    frequencies (more than 3% apart) are returned.
    """
    w = data.omega_rad_s
    s = 1j * w
    bnd = np.maximum(data.bound, 1e-300)
    wx = np.geomspace(float(w.min()), float(w.max()), EXTRA_MODE_GRID_POINTS)[:, None, None]
    z = np.array(EXTRA_MODE_START_ZETAS)[None, :, None]
    den = s[None, None, :] ** 2 + 2 * z * wx * s[None, None, :] + wx**2
    target = (residual[None, None, :] - b1 * s / den) / bnd
    col = (1.0 / den) / bnd
    b0 = np.real(np.sum(np.conj(col) * target, axis=-1)) / np.sum(np.abs(col) ** 2, axis=-1)
    score = np.sum(np.abs(target - b0[..., None] * col) ** 2, axis=-1)
    best_z = np.argmin(score, axis=1)
    per_w = score[np.arange(score.shape[0]), best_z]
    starts: list = []
    chosen: list = []
    for i in np.argsort(per_w):
        wi = float(wx[i, 0, 0])
        if any(abs(wi / c - 1.0) < 0.03 for c in chosen):
            continue
        zi = float(z[0, best_z[i], 0])
        starts.append([2 * zi * wi, wi * wi, b1, float(b0[i, best_z[i]])])
        chosen.append(wi)
        if len(starts) >= n_starts:
            break
    return starts


def fit_extra_mode(data: FrequencyData, box: ModalBox, modal0: np.ndarray, residual: np.ndarray, polish: bool = True) -> CandidateFit:
    """An added mode, started by :func:`extra_mode_starts` on the residual of a least-squares
    fit of the modal structure.

    Its natural frequency is bounded to the measured band, its damping to the prior's
    ``zeta_max``, ``b1`` follows :meth:`ModalBox.b1_rule`.
    """
    w = data.omega_rad_s
    b1_lo, b1_hi = box.b1_rule()
    zmax = box.zeta_max()
    w_lo, w_hi = float(w.min()), float(w.max())
    lo_e = np.array([2 * ZETA_FLOOR * w_lo, w_lo**2, b1_lo, -np.inf])
    hi_e = np.array([2 * zmax * w_hi, w_hi**2, b1_hi, np.inf])
    b1 = b1_lo if b1_lo == b1_hi else 0.0
    ls = fit_minimax("none", box.n_modes, modal0, np.asarray(box.lower).ravel(), np.asarray(box.upper).ravel(),
                     data.omega_rad_s, data.response, data.bound, minimax=False)
    ls_residual = data.response - model_response("none", ls.theta, box.n_modes, w)[0]
    starts = extra_mode_starts(data, ls_residual, b1) + extra_mode_starts(data, residual, b1, 1)
    typical = np.array([max(abs(starts[0][0]), 1e-3), starts[0][1], 1.0, max(abs(starts[0][3]), 1e-6)])
    return _best_of_starts("extra_mode", data, box, ls.theta, starts, lo_e, hi_e, typical, polish)


def fit_candidate(name: str, data: FrequencyData, box: ModalBox, none: CandidateFit, polish: bool = True) -> CandidateFit:
    """Fit one effect candidate starting from the ``none`` fit ``none``."""
    modal0 = none.theta
    residual = data.response - none.response(data.omega_rad_s)
    if name == "none":
        return none
    if name == "time_delay":
        return fit_time_delay(data, box, modal0, polish)
    if name == "first_order_lag":
        return fit_first_order_lag(data, box, modal0, polish)
    if name == "feedthrough":
        return fit_feedthrough(data, box, modal0, residual, polish)
    if name == "residual_mass":
        return fit_residual_mass(data, box, modal0, residual, polish)
    if name == "extra_mode":
        return fit_extra_mode(data, box, modal0, residual, polish)
    raise ValueError(f"effect: expected one of {CANDIDATE_EFFECTS}, found {name!r}")
