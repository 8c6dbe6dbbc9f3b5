"""A closed-loop point from the sums a real-time target's own analyser returns (issue 45).

A target with no recorder beside it (the reference firmware on a board: ``ANALYSE``,
``SUMS?``, docs/real-time-target.md) sums, over ``N`` samples at its rate, each signal ``v`` (the
injection ``r``, the drive ``u``, the sensor ``y``) times the injection's phase
``theta_n = omega n / fs``: ``sum v sin``, ``sum v cos``, ``sum v``, ``sum v^2``, and the
reference's own ``sum sin^2``, ``sum sin cos``, ``sum sin``, ``sum cos^2``, ``sum cos``.

These are the sufficient statistics of the IEEE-1057 three-parameter fit
``v ~ a sin(theta) + b cos(theta) + c`` (:func:`~setmem_hil.estimation.sine_fit.fit_sine`
without transient poles): the normal equations ``M [a b c]^T = [sum v sin, sum v cos, sum v]``
with ``M`` the reference's Gram matrix, the residual ``RSS = sum v^2 - [a b c] . rhs``, the
noise ``s^2 = RSS / (N - 3)`` and the covariance ``s^2 M^-1``. :func:`sine_fit_from_sums` returns
the same :class:`~setmem_hil.estimation.sine_fit.SineFit` as the fit on the samples would
(phasor ``Y = b - j a`` in ``v ~ Re(Y e^{j theta})``), so the ratios and their bounds are
:func:`~setmem_hil.estimation.closed_loop_point.closed_loop_point`'s. What sums cannot give: the
free part's frequency (no samples are kept on the target), and the transient-pole refinement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.closed_loop_point import CONFIDENCE, ClosedLoopPoint
from setmem_hil.estimation.sine_fit import SineFit, confidence_radius, phasor_ratio

__all__ = ["AnalyserSums", "sine_fit_from_sums", "closed_loop_point_from_sums"]


@dataclass(frozen=True)
class AnalyserSums:
    """What ``SUMS?`` returned after one ``ANALYSE``: per signal ``(sum v sin, sum v cos, sum v,
    sum v^2)``; ``reference``: ``(sum sin^2, sum sin cos, sum sin, sum cos^2, sum cos)``."""

    omega_rad_s: float
    fs_hz: float
    first_n: int  # the injection's sample index of the first summed sample
    count: int
    r: tuple[float, float, float, float]
    u: tuple[float, float, float, float]
    y: tuple[float, float, float, float]
    reference: tuple[float, float, float, float, float]
    peak_drive: float
    peak_response: float
    f: tuple[float, float, float, float] | None = None  # the force channel's sums (``SUMS? F``), None without one

    @property
    def response_rms(self) -> float:
        """The sensor's rms about its mean over the summed samples."""
        mean = self.y[2] / self.count
        return math.sqrt(max(self.y[3] / self.count - mean * mean, 0.0))

    def as_arrays(self) -> dict:
        """The sums as arrays (for a record file)."""
        return {"omega_rad_s": self.omega_rad_s, "fs_hz": self.fs_hz, "first_n": self.first_n, "count": self.count,
                "sums_r": np.array(self.r), "sums_u": np.array(self.u), "sums_y": np.array(self.y),
                "sums_reference": np.array(self.reference), "peak_drive": self.peak_drive, "peak_response": self.peak_response,
                **({"sums_f": np.array(self.f)} if self.f is not None else {})}


def sine_fit_from_sums(signal: tuple[float, float, float, float], reference: tuple[float, ...], count: int,
                       omega_rad_s: float) -> SineFit:
    """The three-parameter fit of one signal from its sums (see the module docstring); the
    phase reference is the injection's sample 0."""
    ss, sc, s, cc, c = reference
    gram = np.array([[ss, sc, s], [sc, cc, c], [s, c, float(count)]])
    rhs = np.array(signal[:3], float)
    if count <= 3 or np.linalg.cond(gram) > 1e12:
        raise DataQualityError(f"analyser sums at {omega_rad_s:.4g} rad/s: {count} samples do not determine a sine "
                               "(too few, or too short a part of a period)")
    inverse = np.linalg.inv(gram)
    a, b, offset = inverse @ rhs
    rss = max(float(signal[3]) - float(np.array([a, b, offset]) @ rhs), 0.0)
    s2 = rss / (count - 3)
    cov_ab = s2 * inverse[:2, :2]
    # (Re Y, Im Y) = (b, -a)
    covariance = np.array([[cov_ab[1, 1], -cov_ab[1, 0]], [-cov_ab[0, 1], cov_ab[0, 0]]])
    return SineFit(phasor=complex(b, -a), covariance=covariance, offset=float(offset), noise_rms=math.sqrt(s2), n_samples=int(count),
                   n_params=3, poles=(), transient_amplitudes=(), omega_rad_s=float(omega_rad_s), t_ref_s=0.0)


def closed_loop_point_from_sums(sums: AnalyserSums, confidence: float = CONFIDENCE) -> ClosedLoopPoint:
    """``S = U/R`` and ``G = Y/U`` with their bounds, and the response's free part, from the sums;
    with a force channel also ``A = F/U`` (the actuator's path, drive to force) and its bound."""
    fr, fu, fy = (sine_fit_from_sums(v, sums.reference, sums.count, sums.omega_rad_s) for v in (sums.r, sums.u, sums.y))
    S, cov_s = phasor_ratio(fu, fr)
    G, cov_g = phasor_ratio(fy, fu)
    free_rms = fy.noise_rms * math.sqrt((sums.count - 3) / sums.count)  # the residual's rms, as from samples
    A, A_bound = complex(math.nan, math.nan), math.nan
    if sums.f is not None:
        A, cov_a = phasor_ratio(sine_fit_from_sums(sums.f, sums.reference, sums.count, sums.omega_rad_s), fu)
        A_bound = confidence_radius(cov_a, confidence)
    return ClosedLoopPoint(sums.omega_rad_s, S, confidence_radius(cov_s, confidence), G, confidence_radius(cov_g, confidence),
                           float(abs(fr.phasor)), sums.peak_drive, sums.peak_response, float(abs(fy.phasor)), free_rms, math.nan,
                           A, A_bound)
