"""When a closed-loop point falls outside its prediction, name what the loop does that the model
does not (issue 45).

With the loop closed, ``u = r + g K_eff G u``, so the compensator the loop actually applied is
``K_eff = (1 - 1/S) / (g G)`` from the measured ``S = u/r`` and ``G = y/u`` at each point. Its
ratio to the compensator the target should run, ``rho = K_eff / K_impl``, is 1 when the model of
the implementation is right; the effects the open-loop discrepancy workflow names
(:mod:`setmem_hil.discrepancy.effect_models`) appear here as:

* ``time_delay``: ``rho = exp(-j w tau)`` (more delay than the target's stated samples);
* ``first_order_lag``: ``rho = 1 / (1 + j w / w_c)`` (an anti-alias or amplifier lag);
* ``loop_gain``: ``rho = k`` (the compensator applied with the wrong gain: a DAC or amplifier).

Each is fitted to ``rho`` over the step's points by least squares; the smallest residual names
the effect, when it explains clearly more than ``rho = 1`` does.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar

from setmem_hil.robust.implemented_loop import implemented_response

__all__ = ["closed_loop_discrepancy", "EFFECTS"]

EFFECTS = ("time_delay", "first_order_lag", "loop_gain")
EXPLAINS = 0.25
"""An effect is named when its residual is below this fraction of the residual of ``rho = 1``."""


def _ratios(points, setup) -> tuple[np.ndarray, np.ndarray]:
    w = np.array([p.measured.omega_rad_s for p in points])
    k = implemented_response(setup.controller, setup.fs_hz, setup.delay_samples, setup.prewarp_rad_s, w)
    S = np.array([p.measured.S for p in points])
    G = np.array([p.measured.G for p in points])
    gains = np.array([p.gain for p in points])
    return w, (1.0 - 1.0 / S) / (gains * G * k)


def _fit_one(model, w: np.ndarray, rho: np.ndarray, bounds: tuple[float, float]) -> tuple[float, float]:
    """Least squares over one parameter: a fine grid first (a delay's residual has a minimum at
    every phase wrap), then a bounded search between the best grid point's neighbours."""
    def residual(x: float) -> float:
        return float(np.sum(np.abs(rho - model(w, x)) ** 2))

    grid = np.linspace(bounds[0], bounds[1], 4001)
    values = np.array([residual(x) for x in grid])
    i = int(np.argmin(values))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(residual, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12 * max(1.0, abs(hi))})
    return (float(res.x), float(res.fun)) if res.fun <= values[i] else (float(grid[i]), float(values[i]))


def closed_loop_discrepancy(points, setup) -> dict:
    """``{"effect", "parameters", "residual", "residual_as_modelled", "points"}`` over the step with
    the first point outside (the points of that gain)."""
    first = next(p for p in points if p.outside)
    step = [p for p in points if p.gain == first.gain]
    w, rho = _ratios(step, setup)
    as_modelled = float(np.sum(np.abs(rho - 1.0) ** 2))
    w_max = float(np.max(w))
    fits = {
        "time_delay": (lambda ww, tau: np.exp(-1j * ww * tau), (0.0, 10.0 * math.pi / w_max), "delay_s"),
        "first_order_lag": (lambda ww, lw: 1.0 / (1.0 + 1j * ww / math.exp(lw)), (math.log(0.01 * w_max), math.log(1e4 * w_max)),
                            "corner_rad_s"),
        "loop_gain": (lambda ww, g: np.full(ww.shape, g, dtype=complex), (0.01, 100.0), "gain"),
    }
    results = {}
    for name, (model, bounds, label) in fits.items():
        x, residual = _fit_one(model, w, rho, bounds)
        value = math.exp(x) if name == "first_order_lag" else x
        results[name] = (residual, {label: value})
    best = min(results, key=lambda name: results[name][0])
    named = results[best][0] < EXPLAINS * as_modelled
    return {"effect": best if named else "unexplained", "parameters": results[best][1] if named else {},
            "residual": results[best][0], "residual_as_modelled": as_modelled,
            "fits": {name: {"residual": r, **params} for name, (r, params) in results.items()},
            "points": [{"omega_rad_s": float(ww), "rho_re": float(r.real), "rho_im": float(r.imag)} for ww, r in zip(w, rho)]}
