"""What a sampled instrument's channel may be off by, and what that does to a ratio (issue 26).

A sampled force or response channel's fitted phasor ``X_hat`` differs from the sensor's true
``X`` by instrument errors that no amount of averaging removes (pure numerics, no I/O):

    X_hat = X (1 + eps) + alpha,   |eps| <= relative,   |alpha| <= absolute

* ``relative``: the sensor's calibration (``calibration_uncertainty``); the vertical gain
  accuracy, which datasheets state as a fraction of *full scale* (``divisions x V/div``) and
  performance-verification procedures measure as a *slope*: the gain between DC levels about
  three divisions either side of the centre, the slope's error times the 75 % of full scale
  that span covers (Rigol's performance verification guides: ``|(V1 - V2) - (Vin1 - Vin2)| /
  full scale`` with the inputs at +-3 divisions; Agilent/Keysight: ``DCGainError = (dV_scope /
  dV_in - 1) x 75``; Siglent and Tektronix state the slope's error directly). The channel's gain is therefore within
  ``gain_accuracy / 0.75`` of nominal, which scales the signal's phasor whatever else the record
  holds (an earlier mode still ringing, the range it forced). And the phase error of the timing
  (``omega x trigger_jitter_s``, a stand-in for the channels' skew, which no datasheet states:
  the jitter itself moves every channel alike and cancels in the ratio);
* ``absolute`` (in the channel's units, amplitude): the quantization. With ``q`` one code of an
  ADC spanning 1.5 screens (``1.5 x full scale / 2^bits``; the DS1000Z's spans 1.28, the
  InfiniiVision's 1.25: never smaller than the true code), every sample is within ``q / 2`` of
  the truth, so a sine fit's amplitude moves by at most ``(4 / pi) q / 2 < q``: the term is
  ``q``, unless the channel's own analog noise dithers the quantizer. With Gaussian noise of rms
  ``sigma`` before the ADC, the quantization error's mean given the signal is at most
  ``(q / pi) sum_k exp(-2 pi^2 k^2 sigma^2 / q^2) / k`` (its Fourier series, Widrow and Kollar,
  *Quantization Noise*, 2008, ch. 5); the rest of the error is noise, in the residuals the
  confidence radius is computed from. The term is then ``4 / pi`` times that mean: for
  ``sigma = q / 2`` it is 0.7 % of a code. ``sigma`` is measured on each channel with the output
  off (records forced without a trigger, :meth:`ScpiScope.noise_divisions`), the smallest of
  the scales tried, less the quantization's own ``q^2 / 12``: an underestimate, so the term
  errs large.

The sample clock's accuracy scales every channel's time axis alike: the fitted phasors of force
and response are attenuated and turned by the same factor, so their ratio does not move to first
order, and the term is not added (the driver instead refuses a record whose clock error could
turn the phasors by more than :data:`MAX_CLOCK_PHASE_RAD`).

:func:`ratio_error_bound` is the worst case of ``|g_hat - g|`` for ``g = Y / F`` over every
error within these discs (exact up to the product term, checked by brute force in the tests).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["ChannelError", "ratio_error_bound", "scope_channel_error", "quantization_bias", "measured_quantization_bias", "adc_code", "MAX_CLOCK_PHASE_RAD", "GAIN_TEST_SPAN"]

GAIN_TEST_SPAN = 0.75  # of full scale: the span over which the gain accuracy is verified (module docstring)
MAX_CLOCK_PHASE_RAD = 0.5  # omega x clock error x record length above this: the record is refused (the sinc attenuation, common to every channel, would pass 1 %)


@dataclass(frozen=True)
class ChannelError:
    """One channel's instrument error discs (module docstring): ``absolute`` in the channel's
    units (amplitude), ``relative`` a fraction of the signal."""

    absolute: float = 0.0
    relative: float = 0.0


def adc_code(full_scale: float, adc_bits: int) -> float:
    """One ADC code as these bounds count it: an ADC spanning 1.5 screens of ``full_scale``
    (module docstring: never smaller than a DS1000Z's or an InfiniiVision's true code), in the
    units of ``full_scale`` (volts, or divisions)."""
    return 1.5 * full_scale / 2.0 ** adc_bits


def quantization_bias(q: float, noise_rms: float) -> float:
    """The largest shift of a sine fit's amplitude from quantizing with step ``q`` a signal
    carrying Gaussian noise of rms ``noise_rms`` (module docstring); at most ``q``."""
    ratio = noise_rms / q
    if ratio < 0.2:  # too little noise to count on: the worst case
        return q
    terms = sum(math.exp(-2 * math.pi**2 * k * k * ratio * ratio) / k for k in range(1, 50))
    return min(q, 4 / math.pi * q / math.pi * terms)


def measured_quantization_bias(q: float, measured_noise_rms: float) -> float:
    """:func:`quantization_bias` dithered by a channel's noise as measured through its ADC:
    the measurement holds the quantization's own ``q^2 / 12``, which is no dither and comes off."""
    return quantization_bias(q, math.sqrt(max(0.0, measured_noise_rms**2 - q * q / 12.0)))


def scope_channel_error(*, gain_accuracy: float, full_scale_v: float, adc_bits: int, volt_per_unit: float, calibration: float,
                        omega_rad_s: float, trigger_jitter_s: float, noise_v: float = 0.0, matched_gain: tuple[float, float] | None = None) -> ChannelError:
    """A scope channel's discs from its datasheet figures, the vertical scale it recorded at and
    its measured analog noise ``noise_v`` (rms volts at the ADC, quantization included).

    ``matched_gain``: ``(gain, bound)`` of a channel match at this scale (the signal is divided
    by ``gain``; :mod:`setmem_hil.estimation.channel_match`): the gain term is then ``bound``
    instead of the datasheet's accuracy, and the quantization is in the divided signal's units."""
    q = adc_code(full_scale_v, adc_bits)
    gain, gain_term = (1.0, gain_accuracy / GAIN_TEST_SPAN) if matched_gain is None else matched_gain
    return ChannelError(measured_quantization_bias(q, noise_v) / volt_per_unit / gain, calibration + gain_term + omega_rad_s * trigger_jitter_s)


def ratio_error_bound(g_hat: complex, force_amplitude: float, force: ChannelError, response: ChannelError) -> float:
    """The largest ``|g_hat - g|`` (``g = Y / F`` the truth) with both channels' errors within
    their discs; ``force_amplitude`` is ``|F_hat|`` (the same units as ``force.absolute``).

    ``g = g_hat u1 u2`` with ``u1 = (1 - alpha_Y / Y_hat) / (1 - alpha_F / F_hat)`` and
    ``u2 = (1 + eps_F) / (1 + eps_Y)``; ``|u1 - 1| <= (rho_Y + rho_F) / (1 - rho_F)``,
    ``|u2 - 1| <= (c_F + c_Y) / (1 - c_Y)`` and ``|u1 u2 - 1| <= d1 + d2 + d1 d2``. Infinite
    when the force is not larger than its own error (``rho_F >= 1``) or ``c_Y >= 1``.
    """
    if force_amplitude <= force.absolute or response.relative >= 1.0:
        return math.inf
    rho_f = force.absolute / force_amplitude
    # |g_hat| rho_Y = A_Y / |F_hat|: finite even where the response is near zero
    g_d1 = (response.absolute / force_amplitude + abs(g_hat) * rho_f) / (1.0 - rho_f)
    d1 = (response.absolute / force_amplitude / max(abs(g_hat), 1e-300) + rho_f) / (1.0 - rho_f)
    d2 = (force.relative + response.relative) / (1.0 - response.relative)
    return float(g_d1 + abs(g_hat) * d2 + min(g_d1 * d2, abs(g_hat) * d1 * d2))
