"""Lock-in phasor readings to a frequency-response point with a bound (pure numerics).

A stepped-sine rig with two lock-in amplifiers gives, at each reading ``k``, the RMS phasors
``F_k`` (force sensor, volts) and ``R_k`` (response sensor, volts) at the drive frequency. With the
declared sensitivities ``s_f`` (V per N) and ``s_r`` (V per response unit) each reading gives one
estimate of the receptance

    g_k = (R_k / s_r) / (F_k / s_f)

(the measured force is what counts: the drive gain only plans the level). The lock-in outputs are
low-pass filtered noise, so readings closer than a few time constants are correlated; the driver
spaces them by the filter's settling time (10 tau at 24 dB/oct) and treats them as independent.

**Settling** (:func:`settling_test`): the two halves of the last ``2 m`` readings must agree; their
difference of means is tested against the scatter of the second half (an F test on circular
complex noise) at ``confidence``; the driver asks for two windows in a row. A fixed model-based wait cannot be trusted:
the prior's damping lower bound is 0.

**Bound** (:func:`phasor_point`), for the mean ``g`` of the window, is the sum of

* the noise radius: the confidence disc of the mean for circular complex noise (F test);
* the drift: the full difference of the halves' means (a transient not yet decayed biases the
  mean by about that much; it is zero on average once settled);
* the calibration: with each sensitivity within ``c`` (relative) of its declared value the ratio
  is within ``|g| (c_f + c_r) / (1 - c_r)`` of the truth.

Readings of a transient that decays much slower than the window lasts cannot be told from
steady state by any test on the window. Two things cover it: the dwell's wait and allowance from
the pole intervals (:mod:`setmem_hil.estimation.ringdown`), and, where the intervals do not bound
the damping yet, :func:`exponential_gap`: every reading since the last drive change is fitted
with one decaying (or beating) exponential, and where that fit is significantly better than a
constant, the distance from the window's mean to the fit's limit joins the bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

__all__ = ["PhasorPoint", "settling_test", "noise_radius", "calibration_radius", "phasor_point", "exponential_gap",
           "exponential_trend"]


@dataclass(frozen=True)
class PhasorPoint:
    """A measured point and its bound's parts (absolute, in the model's units)."""

    response: complex
    bound: float
    noise: float
    drift: float
    calibration: float
    force_amplitude: float  # peak, from the mean force reading (force units)
    n_readings: int


def _circular_variance(z: np.ndarray, scale: float) -> float:
    """Per-component noise variance of circular complex readings (``2 (n - 1)`` degrees of
    freedom); a floor keeps noise-free readings well posed."""
    v = float(np.sum(np.abs(z - z.mean()) ** 2)) / (2 * (z.size - 1))
    return max(v, (1e-12 * max(scale, 1e-300)) ** 2)


def settling_test(readings: np.ndarray, confidence: float = 0.99) -> bool:
    """Do the two halves of ``readings`` (complex, even count >= 6) agree within the noise?

    The noise is estimated from the *second* half only (a decaying transient inflates the
    first half's scatter and would hide itself), as circular complex noise (the lock-in's X and
    Y noise are independent with equal variance): ``|d|^2 / (2 s^2 (1/n1 + 1/n2))`` against
    ``F_{2, 2 (n2 - 1)}(confidence)``, ``d`` the difference of the halves' means.
    """
    z = np.asarray(readings, dtype=complex)
    n = z.size
    if n < 6 or n % 2:
        raise ValueError(f"settling_test: expected an even number >= 6 of readings, found {n}")
    a, b = z[: n // 2], z[n // 2:]
    d = complex(a.mean() - b.mean())
    var = _circular_variance(b, float(np.abs(z).mean()))
    h = n // 2
    statistic = abs(d) ** 2 / (2 * var * (2.0 / h))
    return statistic <= stats.f.ppf(confidence, 2, 2 * (h - 1))


def noise_radius(readings: np.ndarray, confidence: float = 0.99) -> float:
    """Radius of a disc holding the true mean with probability >= ``confidence`` (circular
    complex noise: ``|mean - truth|^2 / (2 s^2 / n) ~ F(2, 2 (n - 1))``)."""
    z = np.asarray(readings, dtype=complex)
    n = z.size
    if n < 3:
        raise ValueError(f"noise_radius: expected at least 3 readings, found {n}")
    var = _circular_variance(z, float(np.abs(z).mean()))
    return math.sqrt(2 * var / n * stats.f.ppf(confidence, 2, 2 * (n - 1)))


def calibration_radius(response: complex, force_rel: float, response_rel: float) -> float:
    """Worst-case error of a ratio whose sensitivities are each within a relative tolerance."""
    if not 0 <= response_rel < 1 or force_rel < 0:
        raise ValueError(f"calibration uncertainties must be in [0, 1), found {force_rel}, {response_rel}")
    return abs(response) * (force_rel + response_rel) / (1.0 - response_rel)


def phasor_point(force_v: np.ndarray, response_v: np.ndarray, force_volt_per_unit: float, response_volt_per_unit: float,
                 force_calibration: float = 0.0, response_calibration: float = 0.0, confidence: float = 0.99) -> PhasorPoint:
    """The point ``g`` and its bound from simultaneous force and response readings (V RMS)."""
    F = np.asarray(force_v, dtype=complex) / force_volt_per_unit
    R = np.asarray(response_v, dtype=complex) / response_volt_per_unit
    if F.size != R.size or F.size < 6 or F.size % 2:
        raise ValueError(f"phasor_point: expected the same even number >= 6 of force and response readings, found {F.size}, {R.size}")
    if np.any(np.abs(F) == 0):
        raise ValueError("phasor_point: a force reading is zero (output off, or the force sensor is not connected)")
    g = R / F
    mean = complex(g.mean())
    half = g.size // 2
    drift = abs(complex(g[:half].mean() - g[half:].mean()))
    noise = noise_radius(g, confidence)
    cal = calibration_radius(mean, force_calibration, response_calibration)
    return PhasorPoint(
        response=mean, bound=noise + drift + cal, noise=noise, drift=drift, calibration=cal,
        force_amplitude=math.sqrt(2.0) * abs(complex(F.mean())), n_readings=int(g.size),
    )


def exponential_gap(times_s: np.ndarray, ratios: np.ndarray, window_mean: complex, confidence: float = 0.99) -> float:
    """How far the steady state may lie from ``window_mean`` by the trend of all readings
    (:func:`exponential_trend`'s gap)."""
    return exponential_trend(times_s, ratios, window_mean, confidence)[0]


def exponential_trend(times_s: np.ndarray, ratios: np.ndarray, window_mean: complex,
                      confidence: float = 0.99) -> tuple[float, float]:
    """How far the steady state may lie from ``window_mean`` by the trend of all readings.

    Fits ``g + c exp(s t)`` (``s = -sigma + j beat``; a free oscillation of one mode seen by the
    lock-in) to the readings ``ratios`` at ``times_s`` by least squares over a grid of ``s``
    (decay times from a twentieth to 20 times the span; beats up to four times the Nyquist
    frequency of the mean spacing: irregular readings see past it), ``g`` and ``c`` linear. When the fit explains significantly more than a constant (F
    test with 4 and ``2 n - 6`` degrees of freedom at ``confidence``), returns ``|g - window_mean|``
    and the fitted transient's amplitude at the last reading ``|c exp(s t_n)|`` (0 where it is within
    the fit's residual noise: decayed); else (0, 0). A judgement where the thesis is silent: one exponential, the slowest mode's, is what a
    lock-in dwell's trend shows; more would need more readings than a dwell takes.
    """
    t = np.asarray(times_s, dtype=float)
    z = np.asarray(ratios, dtype=complex)
    n = z.size
    if n < 8:
        return 0.0, 0.0
    t = t - t[0]
    span = float(t[-1])
    if span <= 0:
        return 0.0, 0.0
    rss0 = float(np.sum(np.abs(z - z.mean()) ** 2))
    sigmas = np.geomspace(0.05 / span, 20.0 / span, 30)
    beats = np.linspace(-4 * np.pi * n / span, 4 * np.pi * n / span, 321)  # irregular readings see past the mean Nyquist
    s = (-sigmas[:, None] + 1j * beats[None, :]).ravel()
    e = np.exp(np.outer(s, t))  # (grid, n)
    # least squares of z on [1, e] for every grid point, in closed form (2 x 2 normal equations)
    se, see = e.sum(axis=1), np.sum(np.abs(e) ** 2, axis=1)
    sz, sez = z.sum(), e.conj() @ z
    det = n * see - np.abs(se) ** 2
    ok = det > 1e-12 * n * see
    g = np.where(ok, (see * sz - se * sez) / np.where(ok, det, 1.0), z.mean())
    c = np.where(ok, (n * sez - se.conj() * sz) / np.where(ok, det, 1.0), 0.0)
    rss = np.sum(np.abs(z[None, :] - g[:, None] - c[:, None] * e) ** 2, axis=1)
    rss = np.where(ok, rss, rss0)
    best = int(np.argmin(rss))
    rss1 = float(rss[best])
    dof = 2 * n - 6
    now = float(abs(c[best] * e[best, -1]))
    if rss1 <= 0 or dof <= 0:
        return float(abs(g[best] - window_mean)), now
    statistic = ((rss0 - rss1) / 4.0) / (rss1 / dof)
    if statistic <= stats.f.ppf(confidence, 4, dof):
        return 0.0, 0.0
    # the transient now, where it stands out of the fit's own residual noise (else it has decayed)
    residual_radius = math.sqrt(2 * rss1 / dof * stats.f.ppf(confidence, 2, dof))
    return float(abs(g[best] - window_mean)), (now if now > residual_radius else 0.0)
