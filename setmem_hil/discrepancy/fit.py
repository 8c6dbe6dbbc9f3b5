"""Minimax fit of an augmented modal model: the smallest worst normalised residual.

The set-membership condition of the thesis (eq. 3.8) asks for parameters with
``|g(j omega_i) - G(j omega_i; theta)| <= R(omega_i)`` at every data point. Its exact, non-convex
form is what a missing effect violates, so the discrepancy workflow measures it directly:

    rho(theta) = max_i |g_i - G(j omega_i; theta)| / R_i        (normalised residual)

and ``min_theta rho`` over a box of parameters is the smallest factor by which the bounds must be
inflated for the structure to be consistent with the data (``<= 1``: consistent, eq. 3.8 holds).

The model is a modal model (eq. 3.6) times or plus one *effect* (see
:mod:`setmem_hil.discrepancy.effects`): ``none``, ``time_delay`` ``G e^{-s tau}``,
``first_order_lag`` ``G / (tau s + 1)``, ``feedthrough`` ``G + d`` or ``extra_mode``
``G + (b1 s + b0) / (s^2 + a1 s + a0)``. The parameter vector is the modal values
``(a1, a0, b1, b0)`` per mode, flattened, followed by the effect's parameters.

The fit is local: a bounded Gauss-Newton least-squares fit of the normalised residuals
(``scipy.optimize.least_squares``) finds the basin, then SLSQP minimises the worst residual
(``min t`` s.t. ``|r_i|^2 <= t^2``) from there. Analytic Jacobians (derivatives of eq. 3.9).
Parameters whose lower and upper bounds coincide are held fixed.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, minimize

from setmem_hil.discrepancy.effect_models import EFFECT_MODELS, ExtraMode

EFFECT_PARAM_NAMES: dict[str, tuple[str, ...]] = {
    "none": (),
    **{name: model.param_names for name, model in EFFECT_MODELS.items()},
    ExtraMode.name: ExtraMode.param_names,
}


def model_response(effect: str, theta: np.ndarray, n_modes: int, omega_rad_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Response of the augmented model and its Jacobian with respect to ``theta``.

    Parameters
    ----------
    effect : str
        One of :data:`EFFECT_PARAM_NAMES`.
    theta : ndarray
        ``4 n_modes`` modal values (a1, a0, b1, b0 per mode) then the effect's parameters.
    n_modes : int
        Number of modes of the base (modal) model.
    omega_rad_s : ndarray
        Frequencies.

    Returns
    -------
    G : ndarray, complex, shape (N,)
    J : ndarray, complex, shape (N, len(theta))
        ``dG / dtheta``: per mode (eq. 3.9) ``dG/da1 = -s N/D^2``, ``dG/da0 = -N/D^2``,
        ``dG/db1 = s/D``, ``dG/db0 = 1/D``.
    """
    if effect not in EFFECT_PARAM_NAMES:
        raise ValueError(f"effect: expected one of {tuple(EFFECT_PARAM_NAMES)}, found {effect!r}")
    theta = np.asarray(theta, dtype=float)
    w = np.asarray(omega_rad_s, dtype=float)
    s = 1j * w
    n_modal = 4 * n_modes + (4 if effect == "extra_mode" else 0)
    modal = theta[:n_modal].reshape(-1, 4)
    a1, a0, b1, b0 = (modal[:, k, None] for k in range(4))
    num = b1 * s + b0
    den = s * s + a1 * s + a0
    gk = num / den
    jm = np.empty((modal.shape[0], 4, w.size), dtype=complex)
    jm[:, 0] = -s * num / den**2
    jm[:, 1] = -num / den**2
    jm[:, 2] = s / den
    jm[:, 3] = 1.0 / den
    jac = np.zeros((w.size, theta.size), dtype=complex)
    jac[:, :n_modal] = jm.transpose(2, 0, 1).reshape(w.size, n_modal)
    g_modal = gk.sum(axis=0)
    if effect in ("none", "extra_mode"):
        return g_modal, jac
    g, d_dg, d_dp = EFFECT_MODELS[effect].response_and_jacobian(g_modal, s, theta[n_modal])
    if d_dg is not None:
        jac[:, :n_modal] *= d_dg[:, None]
    jac[:, n_modal] = d_dp
    return g, jac


def normalized_residual(effect: str, theta: np.ndarray, n_modes: int, omega_rad_s, response, bound) -> np.ndarray:
    """``|g_i - G(j omega_i; theta)| / R_i`` per point (eq. 3.8 divided by its bound)."""
    g, _ = model_response(effect, theta, n_modes, omega_rad_s)
    return np.abs(np.asarray(response) - g) / _safe_bound(bound, response)


def _safe_bound(bound, response) -> np.ndarray:
    r = np.asarray(bound, dtype=float)
    floor = 1e-12 * max(float(np.max(np.abs(response))), 1e-300)
    return np.maximum(r, floor)


@dataclass(frozen=True)
class MinimaxFit:
    """Outcome of :func:`fit_minimax`.

    Attributes
    ----------
    theta : ndarray
        Fitted parameters (modal values then effect parameters).
    max_normalized_residual : float
        ``max_i |g_i - G_i| / R_i`` at ``theta``.
    normalized_residual : ndarray
        Per point.
    """

    theta: np.ndarray
    max_normalized_residual: float
    normalized_residual: np.ndarray


def fit_minimax(
    effect: str,
    n_modes: int,
    theta0: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    omega_rad_s: np.ndarray,
    response: np.ndarray,
    bound: np.ndarray,
    scale: np.ndarray | None = None,
    minimax: bool = True,
    polish: bool = True,
    loss: str = "linear",
) -> MinimaxFit:
    """Fit ``theta`` in the box ``[lower, upper]`` minimising the worst normalised residual.

    Parameters
    ----------
    effect, n_modes
        Model structure (see :func:`model_response`).
    theta0 : ndarray
        Start (clipped into the box).
    lower, upper : ndarray
        Box; equal entries are held fixed; infinite entries are unbounded.
    omega_rad_s, response, bound : ndarray
        The data (eq. 3.7).
    scale : ndarray, optional
        Typical magnitude of each parameter (default ``|theta0|``, or 1 where that is 0).
    minimax : bool
        If False, stop after the least-squares stage (cheaper; used for multi-start screening).
    loss : str
        Loss of the least-squares stage (``scipy.optimize.least_squares``); ``"soft_l1"`` with
        the residuals in units of the bound gives a robust fit that leaves a localised
        discrepancy where it is instead of spreading it (used with ``minimax=False``).
    polish : bool
        If False, skip the final SLSQP stage (the p-norm continuation already gets within a
        few per cent of the minimax value).

    Returns
    -------
    MinimaxFit
    """
    w = np.asarray(omega_rad_s, dtype=float)
    g = np.asarray(response, dtype=complex)
    r_bound = _safe_bound(bound, g)
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    theta0 = np.clip(np.asarray(theta0, dtype=float), lo, hi)
    free = hi > lo
    if scale is None:
        scale = np.abs(theta0)
    scale = np.where(np.asarray(scale, dtype=float) > 0, scale, 1.0)

    def full(y):
        th = theta0.copy()
        th[free] = y * scale[free]
        return th

    def resid_jac(y):
        th = full(y)
        gm, jac = model_response(effect, th, n_modes, w)
        r = (gm - g) / r_bound
        jr = jac[:, free] * (scale[free] / r_bound[:, None])
        return r, jr

    if not np.any(free):
        rho = normalized_residual(effect, theta0, n_modes, w, g, r_bound)
        return MinimaxFit(theta0, float(rho.max()), rho)

    y_lo = lo[free] / scale[free]
    y_hi = hi[free] / scale[free]
    y0 = theta0[free] / scale[free]
    # least_squares wants a strictly interior start
    span = np.where(np.isfinite(y_hi - y_lo), y_hi - y_lo, 1.0)
    y0 = np.clip(y0, y_lo + 1e-9 * span, y_hi - 1e-9 * span)

    def ls_fun(y):
        r, _ = resid_jac(y)
        return np.concatenate([r.real, r.imag])

    def ls_jac(y):
        _, jr = resid_jac(y)
        return np.vstack([jr.real, jr.imag])

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ls = least_squares(ls_fun, y0, jac=ls_jac, bounds=(y_lo, y_hi), method="trf", x_scale="jac", max_nfev=200,
                           loss=loss, f_scale=1.0)
    y_best = ls.x
    rho_best = float(np.abs(resid_jac(y_best)[0]).max())
    if minimax and np.isfinite(rho_best):
        for stage in (_pnorm_stage, _minimax_stage) if polish else (_pnorm_stage,):
            y_mm, rho_mm = stage(resid_jac, y_best, rho_best, y_lo, y_hi)
            if rho_mm < rho_best:
                y_best, rho_best = y_mm, rho_mm
    theta = full(y_best)
    rho = normalized_residual(effect, theta, n_modes, w, g, r_bound)
    return MinimaxFit(theta, float(rho.max()), rho)


def _pnorm_stage(resid_jac, y0, rho0, y_lo, y_hi) -> tuple[np.ndarray, float]:
    """p-norm continuation: least squares on ``(|r_i| / rho0)^(p/2)`` for p = 8, then 32.

    ``sum |r_i|^p`` tends to the max as p grows; each stage starts from the previous one.
    """
    y_best, rho_best = y0, rho0
    y = y0
    for p in (8.0, 32.0):
        h = p / 2.0

        def fun(v, h=h):
            a = np.abs(resid_jac(v)[0]) / rho0
            return a**h

        def jac(v, h=h):
            r, jr = resid_jac(v)
            a = np.abs(r) / rho0
            # d a^h = h a^(h-2) Re(conj(r) dr) / rho0^2
            return (h * a ** (h - 2.0) / rho0**2)[:, None] * np.real(np.conj(r)[:, None] * jr)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            y_start = np.clip(y, np.nextafter(y_lo, np.inf), np.nextafter(y_hi, -np.inf))
            try:
                res = least_squares(fun, y_start, jac=jac, bounds=(y_lo, y_hi), method="trf", x_scale="jac", max_nfev=40)
            except ValueError:
                break
        y = res.x
        rho = float(np.abs(resid_jac(y)[0]).max())
        if np.isfinite(rho) and rho < rho_best:
            y_best, rho_best = y, rho
    return y_best, rho_best


def _minimax_stage(resid_jac, y0, rho0, y_lo, y_hi) -> tuple[np.ndarray, float]:
    """SLSQP on ``min t`` s.t. ``t^2 - |r_i|^2 >= 0`` (the epigraph form of the max).

    Variables are rescaled so every column of the residual Jacobian at the start has unit norm
    (resonant modes make the raw problem very stiff).
    """
    n = y0.size
    _, jr0 = resid_jac(y0)
    col = np.linalg.norm(np.abs(jr0), axis=0)
    col = np.where(np.isfinite(col) & (col > 0), col, 1.0)

    def y_of(z):
        return z[:n] / col

    def cons(z):
        r, _ = resid_jac(y_of(z))
        return z[n] ** 2 - np.abs(r) ** 2

    def cons_jac(z):
        r, jr = resid_jac(y_of(z))
        d = -2.0 * np.real(np.conj(r)[:, None] * jr) / col[None, :]
        return np.hstack([d, 2.0 * z[n] * np.ones((r.size, 1))])

    bounds = [(None if not np.isfinite(a) else a * c, None if not np.isfinite(b) else b * c) for a, b, c in zip(y_lo, y_hi, col)]
    bounds.append((0.0, None))
    z0 = np.append(y0 * col, rho0 * 1.0001)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = minimize(
            lambda z: z[n], z0, jac=lambda z: np.eye(n + 1)[n], method="SLSQP", bounds=bounds,
            constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}], options={"maxiter": 60, "ftol": 1e-8},
        )
    y = np.clip(y_of(res.x), y_lo, y_hi)
    rho = float(np.abs(resid_jac(y)[0]).max())
    if not np.isfinite(rho):
        return y0, rho0
    return y, rho
