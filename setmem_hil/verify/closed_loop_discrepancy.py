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

**At the plant's terminals** (issue 63 item 1). A board's analyser sums the drive *before* its DAC
and the sensor *after* its ADC, so an effect on the analogue side (the amplifier's gain or
bandwidth, the converters' latency, an anti-alias filter) leaves ``K_eff`` the firmware's own
(``rho = 1``) and lands in the measured ``G``: ``G_meas = a(jw) G``. So the same three effects are
also fitted to ``gamma = G_meas / G_box`` (``G_box``: the centre of the box's disc of ``G`` at each
point, :func:`~setmem_hil.robust.closed_loop_prediction.plant_disc`). Both ratios are compared in
units of their own uncertainty (``gamma``: the disc's radius plus the measured ``G``'s bound,
over ``|G_box|``; ``rho``: the measured ``S``'s and ``G``'s bounds, to first order): the side whose
as-modelled ratio (1) is further off, by more than its uncertainty on the whole (a normalised sum
of squares over the number of points), is where the effect is named, with ``where``
``"compensator"`` or ``"plant_terminals"``.

What cannot be told apart without a force channel: an actuator-side effect (the DAC, the
amplifier) and a sensor-side one (the ADC's filter) both multiply ``G``; ``gamma`` names the
effect and its parameter, not its side: ``side`` is ``"actuator or sensor"``.

**The side, from a force channel.** A board whose second ADC reads the force transducer at the
structure's input (``setmem_target_force_sample``, ``SUMS? F``; docs/real-time-target.md) gives
``A = F/U`` at each point besides ``G = Y/U``. The force ADC samples the drive held since the
previous sample, so as modelled ``A = exp(-j w Ts)``; the measured ``gamma`` splits exactly into
the actuator's ratio ``alpha = A exp(j w Ts)`` (drive to force: the DAC, its pipeline, the
amplifier, the shaker's attachment) and the sensor's ``beta = gamma / alpha`` (force to the
firmware's sensor sample over the box's ``G``: the structure beyond the box, the sensor, its
conditioning, the anti-alias filter). The side whose as-modelled ratio is further off, in units of
its own uncertainty per point (``alpha``: the bound of ``A``; ``beta``: ``gamma``'s plus ``A``'s),
is ``side`` (``"actuator"`` / ``"sensor"``), and the effect and its parameter are fitted to that
side's ratio alone. Limits: a filter common to both ADC channels (the same anti-alias filter on
force and sensor) delays ``F`` and ``Y`` alike, so it cancels from ``beta`` and is named on the
actuator's side; a force transducer's own error (sensitivity, its conditioning's lag) is read as
the actuator's, with the opposite sign on the sensor's. ``side`` is ``"actuator or sensor"``
again when neither ratio is off by more than its uncertainty.
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


def _ratios(points, setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w, rho, sigma)``: ``rho = K_eff / K_impl`` and its relative uncertainty to first order
    (``d(1 - 1/S) = dS / S^2``, over ``|1 - 1/S|``; and ``G``'s relative bound)."""
    w = np.array([p.measured.omega_rad_s for p in points])
    k = implemented_response(setup.controller, setup.fs_hz, setup.delay_samples, setup.prewarp_rad_s, w)
    S = np.array([p.measured.S for p in points])
    G = np.array([p.measured.G for p in points])
    gains = np.array([p.gain for p in points])
    sigma = (np.array([p.measured.S_bound for p in points]) / np.maximum(np.abs(S) * np.abs(S - 1.0), 1e-300)
             + np.array([p.measured.G_bound for p in points]) / np.maximum(np.abs(G), 1e-300))
    # the implementation's own model is good to about a sample's phase (where within the sample
    # the held drive acts: measured rho = 1 + j 0.5 w Ts on the clean emulated loop), so rho is
    # not weighed tighter than that
    return w, (1.0 - 1.0 / S) / (gains * G * k), np.maximum(sigma, np.maximum(SIGMA_FLOOR, w / setup.fs_hz))


def _plant_ratios(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(w, gamma, sigma)``: the measured ``G`` over the centre of the box's disc, where the box
    bounds ``G`` (points where a mode's denominator can vanish are left out), and its relative
    uncertainty (the disc's radius plus the measured bound, over the centre)."""
    kept = [p for p in points if p.prediction.plant is not None and np.isfinite(p.prediction.plant.radius)
            and abs(p.prediction.plant.center) > 0]
    w = np.array([p.measured.omega_rad_s for p in kept])
    centre = np.array([p.prediction.plant.center for p in kept], dtype=complex)
    gamma = np.array([p.measured.G for p in kept], dtype=complex) / centre if kept else np.zeros(0, dtype=complex)
    sigma = np.array([(p.prediction.plant.radius + p.measured.G_bound) / abs(p.prediction.plant.center) for p in kept])
    return w, gamma, np.maximum(sigma, SIGMA_FLOOR)


def _side_ratios(points, fs_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(w, alpha, alpha_sigma, beta, beta_sigma)`` at the points with a force channel where the
    box bounds ``G`` (module docstring: ``gamma = alpha beta``)."""
    kept = [p for p in points if p.measured.has_force and p.prediction.plant is not None
            and np.isfinite(p.prediction.plant.radius) and abs(p.prediction.plant.center) > 0]
    w, gamma, gamma_sigma = _plant_ratios(kept)
    A = np.array([p.measured.A for p in kept], dtype=complex)
    alpha = A * np.exp(1j * w / fs_hz)  # the force ADC reads the drive held since the previous sample
    alpha_sigma = np.array([p.measured.A_bound for p in kept]) / np.maximum(np.abs(A), 1e-300)
    beta = gamma / np.where(alpha == 0, 1e-300, alpha)
    return w, alpha, np.maximum(alpha_sigma, SIGMA_FLOOR), beta, np.maximum(gamma_sigma + alpha_sigma, SIGMA_FLOOR)


def _told_side(points, fs_hz: float) -> dict | None:
    """The side of the plant an effect named at its terminals sits on, from the force channel:
    ``{"side", "effect", "parameters", "actuator_fits", "sensor_fits", "off"}``, or None without
    one (fewer than two points with a force channel)."""
    w, alpha, alpha_sigma, beta, beta_sigma = _side_ratios(points, fs_hz)
    if w.size < 2:
        return None
    sides = {"actuator": (alpha, alpha_sigma), "sensor": (beta, beta_sigma)}
    off = {side: float(np.sum(np.abs((ratio - 1.0) / sigma) ** 2)) / w.size for side, (ratio, sigma) in sides.items()}
    fits = {side: _fits(w, ratio, sigma) for side, (ratio, sigma) in sides.items()}
    side = max(off, key=off.get)
    best = min(fits[side], key=lambda name: fits[side][name][0])
    told = off[side] > 1.0
    return {"side": side if told else "actuator or sensor", "effect": best if told else None,
            "parameters": fits[side][best][1] if told else {}, "off": off,
            **{f"{name}_fits": {e: {"residual": r, **params} for e, (r, params) in fit.items()} for name, fit in fits.items()}}


SIGMA_FLOOR = 1e-3
"""The smallest relative uncertainty a ratio is weighed with (0.1 %): a point measured to 1e-6
must not outweigh every other."""


def _fit_one(model, w: np.ndarray, ratio: np.ndarray, sigma: np.ndarray, bounds: tuple[float, float]) -> tuple[float, float]:
    """Weighted least squares over one parameter: a fine grid first (a delay's residual has a
    minimum at every phase wrap), then a bounded search between the best grid point's neighbours."""
    def residual(x: float) -> float:
        return float(np.sum(np.abs((ratio - model(w, x)) / sigma) ** 2))

    grid = np.linspace(bounds[0], bounds[1], 4001)
    values = np.array([residual(x) for x in grid])
    i = int(np.argmin(values))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(residual, bounds=(lo, hi), method="bounded", options={"xatol": 1e-12 * max(1.0, abs(hi))})
    return (float(res.x), float(res.fun)) if res.fun <= values[i] else (float(grid[i]), float(values[i]))


def _effect_models(w_max: float) -> dict:
    return {
        "time_delay": (lambda ww, tau: np.exp(-1j * ww * tau), (0.0, 10.0 * math.pi / w_max), "delay_s"),
        "first_order_lag": (lambda ww, lw: 1.0 / (1.0 + 1j * ww / math.exp(lw)), (math.log(0.01 * w_max), math.log(1e4 * w_max)),
                            "corner_rad_s"),
        "loop_gain": (lambda ww, g: np.full(ww.shape, g, dtype=complex), (0.01, 100.0), "gain"),
    }


def _fits(w: np.ndarray, ratio: np.ndarray, sigma: np.ndarray) -> dict:
    """Each effect fitted to ``ratio``: ``{name: (residual, {parameter: value})}``."""
    results = {}
    for name, (model, bounds, label) in _effect_models(float(np.max(w))).items():
        x, residual = _fit_one(model, w, ratio, sigma, bounds)
        results[name] = (residual, {label: math.exp(x) if name == "first_order_lag" else x})
    return results


def closed_loop_discrepancy(points, setup) -> dict:
    """``{"effect", "parameters", "where", "side", "residual", "residual_as_modelled", "fits",
    "terminal_fits", "points"}`` over the step with the first point outside (the points of that
    gain); see the module docstring for the two ratios and the rule."""
    first = next(p for p in points if p.outside)
    step = [p for p in points if p.gain == first.gain]
    w, rho, rho_sigma = _ratios(step, setup)
    compensator = {"as_modelled": float(np.sum(np.abs((rho - 1.0) / rho_sigma) ** 2)), "n": w.size, "fits": _fits(w, rho, rho_sigma)}
    wg, gamma, gamma_sigma = _plant_ratios(step)
    terminals = {"as_modelled": float(np.sum(np.abs((gamma - 1.0) / gamma_sigma) ** 2)), "n": wg.size,
                 "fits": _fits(wg, gamma, gamma_sigma) if wg.size >= 2 else {}}
    # the side whose as-modelled ratio is further off, in units of its own uncertainty per point
    off = {side: (d["as_modelled"] / d["n"] if d["n"] and d["fits"] else 0.0) for side, d in
           (("compensator", compensator), ("plant_terminals", terminals))}
    where = max(off, key=off.get)
    chosen = compensator if where == "compensator" else terminals
    best = min(chosen["fits"], key=lambda name: chosen["fits"][name][0])
    residual = chosen["fits"][best][0]
    named = off[where] > 1.0 and residual < EXPLAINS * chosen["as_modelled"]
    effect, parameters = (best, chosen["fits"][best][1]) if named else ("unexplained", {})
    side = ("the compensator's path (inside the target)" if where == "compensator" else "actuator or sensor") if named else None
    told = _told_side(step, setup.fs_hz) if named and where == "plant_terminals" else None
    if told is not None and told["effect"] is not None:  # the force channel says which side, and fits it there alone
        side, effect, parameters = told["side"], told["effect"], told["parameters"]
    return {"effect": effect, "parameters": parameters, "where": where if named else None, "side": side,
            **({"side_from_force": told} if told is not None else {}),
            "residual": residual, "residual_as_modelled": chosen["as_modelled"],
            "fits": {name: {"residual": r, **params} for name, (r, params) in compensator["fits"].items()},
            "terminal_fits": {name: {"residual": r, **params} for name, (r, params) in terminals["fits"].items()},
            "points": [{"omega_rad_s": float(ww), "rho_re": float(r.real), "rho_im": float(r.imag)} for ww, r in zip(w, rho)],
            "terminal_points": [{"omega_rad_s": float(ww), "gamma_re": float(g.real), "gamma_im": float(g.imag)}
                                for ww, g in zip(wg, gamma)]}
