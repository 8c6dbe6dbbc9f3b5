"""The closed loop's sensitivity predicted over the box, as a guaranteed outer set (issue 45).

At one frequency ``w`` the plant of the box is ``G = sum_i (b1_i jw + b0_i) / (a0_i - w^2 + j a1_i w)``
with every parameter in its interval (eq. 2.1-2.3), plus the unmodelled dynamics the analysis
allows, an additive ``W1(jw) Delta`` with ``|Delta| <= 1`` (the first complex block of eq.
6.20-6.22; the analysis's robust-performance test is ``|W2 S| + |W1 K S| < 1``). With the
compensator as the target runs it, ``K = K_impl(jw)``
(:func:`~setmem_hil.robust.implemented_loop.implemented_response`), the loop's sensitivity is
``S = 1 / (1 - G K)`` (positive feedback, the drive over the injection at the summing junction).

The set of ``G`` is enclosed in a disc by circular arithmetic (Gargantini and Henrici 1972):
each mode's numerator and denominator range over rectangles, enclosed in their circumscribed
discs; the inverse of a disc not holding 0 is a disc; products and sums of discs are enclosed in
discs (``|c1| r2 + |c2| r1 + r1 r2``, radii added). Every step encloses, so every plant of the box
(and every unmodelled term within ``W1``) has its ``G`` in the disc, and its ``S`` in the inverse
of ``1 - disc K``: a disc too (:class:`PredictedSensitivity`). A measured ``S`` whose own error
disc does not meet it falsifies the model (Smith and Doyle 1992: closed-loop data can invalidate
an uncertain model, never prove it). Where a denominator's disc holds 0 (a resonance whose
frequency interval is wide), nothing is predicted there (``bounded`` false).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import Weights

__all__ = ["Disc", "PredictedSensitivity", "plant_disc", "predicted_sensitivity"]


@dataclass(frozen=True)
class Disc:
    """The complex numbers within ``radius`` of ``center``."""

    center: complex
    radius: float

    def __add__(self, other: "Disc") -> "Disc":
        return Disc(self.center + other.center, self.radius + other.radius)

    def __mul__(self, other: "Disc") -> "Disc":
        return Disc(self.center * other.center,
                    abs(self.center) * other.radius + abs(other.center) * self.radius + self.radius * other.radius)

    def scaled(self, factor: complex) -> "Disc":
        return Disc(self.center * factor, self.radius * abs(factor))

    def inverse(self) -> "Disc | None":
        """``{1/z}`` for ``z`` in the disc: a disc when 0 lies outside, else None."""
        m = abs(self.center)
        if not m > self.radius:
            return None
        denominator = m * m - self.radius * self.radius
        return Disc(np.conj(self.center) / denominator, self.radius / denominator)

    def meets(self, other: "Disc") -> bool:
        return abs(self.center - other.center) <= self.radius + other.radius

    @property
    def abs_range(self) -> tuple[float, float]:
        m = abs(self.center)
        return max(m - self.radius, 0.0), m + self.radius


def _rectangle(re_lo: float, re_hi: float, im_lo: float, im_hi: float) -> Disc:
    return Disc(complex(0.5 * (re_lo + re_hi), 0.5 * (im_lo + im_hi)), 0.5 * float(np.hypot(re_hi - re_lo, im_hi - im_lo)))


def plant_disc(model: IntervalModel, omega_rad_s: float, gain: tuple[float, float] | None = None) -> Disc | None:
    """A disc holding ``G(jw)`` of every plant of ``model`` (times every gain of ``gain``); None
    where a mode's denominator can vanish."""
    w = float(omega_rad_s)
    total = Disc(0j, 0.0)
    for (a1_lo, a0_lo, b1_lo, b0_lo), (a1_hi, a0_hi, b1_hi, b0_hi) in zip(model.lower, model.upper):
        numerator = _rectangle(b0_lo, b0_hi, w * b1_lo, w * b1_hi)
        denominator = _rectangle(a0_lo - w * w, a0_hi - w * w, w * a1_lo, w * a1_hi).inverse()
        if denominator is None:
            return None
        total = total + numerator * denominator
    if gain is not None:
        total = total * Disc(complex(0.5 * (gain[0] + gain[1])), 0.5 * (gain[1] - gain[0]))
    return total


@dataclass(frozen=True)
class PredictedSensitivity:
    """The predicted set of ``S`` at one frequency (a disc), and of ``G`` with the unmodelled term."""

    omega_rad_s: float
    plant: Disc | None
    sensitivity: Disc | None

    @property
    def bounded(self) -> bool:
        return self.sensitivity is not None

    @property
    def abs_range(self) -> tuple[float, float]:
        return self.sensitivity.abs_range if self.sensitivity is not None else (0.0, float("inf"))

    def holds(self, measured: complex, bound: float) -> bool:
        """Is the measured ``S`` (within ``bound``) consistent with the prediction?"""
        return self.sensitivity is None or self.sensitivity.meets(Disc(complex(measured), float(bound)))


def predicted_sensitivity(model: IntervalModel, weights: Weights, k_implemented: complex, omega_rad_s: float,
                          gain: tuple[float, float] | None = None, loop_gain: float = 1.0) -> PredictedSensitivity:
    """The predicted ``S`` at ``omega_rad_s`` for the compensator's value ``k_implemented`` there,
    engaged at ``loop_gain`` (see the module docstring)."""
    g = plant_disc(model, omega_rad_s, gain)
    if g is None:
        return PredictedSensitivity(float(omega_rad_s), None, None)
    g = g + Disc(0j, float(weights.w1_magnitude(omega_rad_s)))
    loop = Disc(1.0 + 0j, 0.0) + g.scaled(-loop_gain * k_implemented)
    return PredictedSensitivity(float(omega_rad_s), g, loop.inverse())
