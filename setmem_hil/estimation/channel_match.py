"""Channel match: every oscilloscope channel's gain at every vertical scale, relative to one
reference, from records of one signal seen by all channels at once (issue 26).

A scope's vertical gain is off by up to its datasheet accuracy (4 % of the signal for a DS1000Z,
:mod:`setmem_hil.estimation.channel_errors`), and a frequency response is a *ratio* of two
channels: without more, every point carries both channels' errors. But the error is a fixed
property of a channel at a scale. Wired to one source through a BNC tee, every channel sees the
same voltage, so records at chosen scales measure the ratios of those fixed gains (what a
dynamic signal analyser's "channel match" calibration does with its internal source).

Record ``r`` puts channel ``c`` at scale ``s``; its fitted amplitude is

    |X_rc| = |G(c, s)| |V_r| (1 + e_rc),   |e_rc| <= delta_rc,

``delta`` the fit's bound (quantization and noise, :func:`amplitude_error_bound`). In logarithms
``log|X| = log|G| + log|V|`` is linear; least squares with ``log|G(reference)| = 0`` gives
``x = P y``, so each estimate's error is ``sum_j P_ij log(1 + e_j)`` and is at most
``sum_j |P_ij| (-log(1 - delta_j))``: a guaranteed bound whatever the errors' distribution.
Records that link a scale to the next one (the reference channel at one scale, the others at
the next, the same signal on both) chain every scale to the reference.

Only magnitudes are matched: a channel-to-channel skew is a delay, whose phase at the
calibration frequency says nothing certain about another frequency (the dwell's bound keeps
its ``omega x trigger_jitter_s`` term).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.estimation.channel_errors import measured_quantization_bias
from setmem_hil.model.channel_match import ChannelGain, scale_key

__all__ = ["MatchRecord", "solve_channel_match", "amplitude_error_bound", "fit_amplitude",
           "NOISE_SIGMAS", "DRIFT_ALLOWANCE"]

NOISE_SIGMAS = 6.0  # the noise part of a record's bound: 6 standard deviations of the fitted amplitude (1e-8 of the time beyond)
DRIFT_ALLOWANCE = 0.001  # per channel: the gains' drift between the calibration and the campaign (same day, same room; not in datasheets)


@dataclass(frozen=True)
class MatchRecord:
    """One record of the tee'd signal: each channel's scale (V/div), fitted amplitude (V) and
    the relative bound ``delta`` of that amplitude."""

    scales_v: dict[int, float]
    amplitudes_v: dict[int, float]
    bounds: dict[int, float]


def fit_amplitude(t_s: np.ndarray, volts: np.ndarray, frequency_hz: float) -> tuple[float, float]:
    """Least-squares sine of known frequency plus offset: ``(amplitude_v, residual_rms_v)``."""
    w = 2 * math.pi * frequency_hz * np.asarray(t_s, dtype=float)
    design = np.column_stack([np.cos(w), np.sin(w), np.ones_like(w)])
    coef, *_ = np.linalg.lstsq(design, volts, rcond=None)
    residual = volts - design @ coef
    return float(math.hypot(coef[0], coef[1])), float(np.sqrt(np.mean(residual**2)))


def amplitude_error_bound(amplitude_v: float, n_samples: int, noise_v: float, code_v: float) -> float:
    """Relative bound on a fitted amplitude: the quantization's bias (dithered by the channel's
    own noise ``noise_v``, rms volts measured with nothing connected; ``code_v`` one ADC code)
    and ``NOISE_SIGMAS`` standard deviations of the fit (``noise_v sqrt(2 / N)``)."""
    absolute = measured_quantization_bias(code_v, noise_v) + NOISE_SIGMAS * noise_v * math.sqrt(2.0 / n_samples)
    return absolute / amplitude_v


def solve_channel_match(records: list[MatchRecord], reference: tuple[int, float]) -> list[ChannelGain]:
    """Every ``(channel, scale)`` the records reach from ``reference`` (module docstring), with
    its guaranteed bound. Raises ValueError when a seen ``(channel, scale)`` is not linked to the
    reference (its gain has no meaning relative to it) or a bound reaches 1."""
    unknowns = sorted({scale_key(c, s) for r in records for c, s in r.scales_v.items()})
    ref = scale_key(*reference)
    if ref not in unknowns:
        raise ValueError(f"channel match: the reference (channel {reference[0]} at {reference[1]:g} V/div) is in no record")
    col = {k: i for i, k in enumerate(k for k in unknowns if k != ref)}
    n_g, n_r = len(col), len(records)
    rows, y, delta = [], [], []
    for r, record in enumerate(records):
        for c, s in record.scales_v.items():
            row = np.zeros(n_g + n_r)
            key = scale_key(c, s)
            if key != ref:
                row[col[key]] = 1.0
            row[n_g + r] = 1.0
            rows.append(row)
            y.append(math.log(record.amplitudes_v[c]))
            d = record.bounds[c]
            delta.append(-math.log1p(-d) if d < 1 else math.inf)
    A = np.array(rows)
    if np.linalg.matrix_rank(A) < A.shape[1]:
        raise ValueError("channel match: some scales are not linked to the reference by the records")
    P = np.linalg.pinv(A)[:n_g]
    x = P @ np.array(y)
    log_bound = np.abs(P) @ np.array(delta)
    out = [ChannelGain(ref[0], ref[1], 1.0, 0.0)]
    for (c, s), i in col.items():
        if not log_bound[i] < math.log(2.0):
            raise ValueError(f"channel match: channel {c} at {s:g} V/div: the records do not bound its gain (bound {log_bound[i]:.3g})")
        out.append(ChannelGain(c, s, float(math.exp(x[i])), float(math.expm1(log_bound[i]))))
    return sorted(out, key=lambda g: (g.channel, g.scale_v))
