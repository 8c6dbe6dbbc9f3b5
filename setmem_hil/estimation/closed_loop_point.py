"""One closed-loop point from a record of the injection, the drive and the response (issue 45).

With the loop closed (positive feedback, injection ``r`` summed into the drive ``u``), the
sensitivity is ``S = U / R`` and the plant in closed loop ``G = Y / U``, each the ratio of two
phasors at the injection's frequency fitted on the same samples (:func:`~setmem_hil.estimation.
sine_fit.fit_sine`, the IEEE-1057 fit), so no timing between channels or instruments enters.
The bounds are confidence radii of the ratios' covariances at the dwells' confidence (first-order
propagation as :func:`~setmem_hil.estimation.sine_fit.phasor_ratio`; the drive's noise is the
response's fed back, so the two channels of ``G`` are not independent: the radius treats them as
if they were, a choice stated here because it is not exact).

The response's **free part** (what the sine at the injection's frequency does not explain: the
sensor's noise, the rig's disturbance, and a transient that has not decayed) is kept beside the
ratios: its rms, the frequency of its largest spectral line, and the forced part's amplitude. A
loop that settled as the box predicts leaves little free part; a loop that rings or grows leaves
a free part larger than the forced one (:mod:`setmem_hil.verify.plan` stops there).
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np

from setmem_hil.estimation.sine_fit import confidence_radius, fit_sine, phasor_ratio

__all__ = ["ClosedLoopPoint", "closed_loop_point", "free_part_peak_omega", "CONFIDENCE"]

CONFIDENCE = 0.9995
"""The dwells' confidence (``DwellSettings.confidence``)."""


@dataclass(frozen=True)
class ClosedLoopPoint:
    omega_rad_s: float
    S: complex
    S_bound: float
    G: complex
    G_bound: float
    injection_amplitude: float
    peak_drive: float
    peak_response: float
    forced_response_amplitude: float = float("nan")  # |Y|: the response's part at the injection's frequency
    free_response_rms: float = float("nan")  # rms of the rest (the fit's residual)
    free_response_omega_rad_s: float = float("nan")  # the rest's largest spectral line
    A: complex = complex(float("nan"), float("nan"))  # F/U: drive to the force at the structure (a force channel; nan: none)
    A_bound: float = float("nan")

    @property
    def has_force(self) -> bool:
        return math.isfinite(self.A_bound)


def free_part_peak_omega(t_s: np.ndarray, residual: np.ndarray) -> float:
    """The frequency (rad/s) of the largest line of ``residual``'s spectrum (Hann window, zero
    padding to 4x): where a transient that has not decayed rings."""
    n = residual.size
    if n < 8:
        return float("nan")
    dt = float(t_s[1] - t_s[0])
    spectrum = np.abs(np.fft.rfft((residual - residual.mean()) * np.hanning(n), 4 * n))
    spectrum[0] = 0.0
    return float(2 * np.pi * np.fft.rfftfreq(4 * n, dt)[int(np.argmax(spectrum))])


def closed_loop_point(t_s: np.ndarray, r: np.ndarray, u: np.ndarray, y: np.ndarray, omega_rad_s: float,
                      confidence: float = CONFIDENCE) -> ClosedLoopPoint:
    """``S = U/R`` and ``G = Y/U`` at ``omega_rad_s`` with their bounds (see the module docstring)."""
    t0 = float(t_s[0])
    fr, fu, fy = (fit_sine(t_s, v, omega_rad_s, t_ref_s=t0) for v in (r, u, y))
    S, cov_s = phasor_ratio(fu, fr)
    G, cov_g = phasor_ratio(fy, fu)
    t = np.asarray(t_s, float)
    residual = np.asarray(y, float) - fy.offset - np.real(fy.phasor * np.exp(1j * omega_rad_s * (t - t0)))
    return ClosedLoopPoint(float(omega_rad_s), S, confidence_radius(cov_s, confidence), G, confidence_radius(cov_g, confidence),
                           float(abs(fr.phasor)), float(np.max(np.abs(u))), float(np.max(np.abs(y))),
                           float(abs(fy.phasor)), float(np.sqrt(np.mean(residual ** 2))), free_part_peak_omega(t, residual))
