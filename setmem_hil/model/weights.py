"""Control-design weights (thesis eq. 6.1 and 6.13), as transfer-function coefficients.

``W1`` bounds the additive unmodelled dynamics; ``W2`` weights the sensitivity (robust
performance: ``|W2 S| <= 1``). For the H2 design ``W2`` gets an extra pole at
``s = -w2_extra_pole_rad_s`` (default 10000) so that its D term vanishes (section 6.3.1).
Coefficients are highest power first (``numpy.polyval`` order).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

_W1_NUM = tuple(float(c) for c in 0.182 * np.polymul([1.0, 15.2, 361.0], [1.0, 15.2, 361.0]))
_W1_DEN = tuple(float(c) for c in np.polymul([1.0, 26.4, 1089.0], [1.0, 26.4, 1089.0]))
_W2_NUM = tuple(float(c) for c in 0.33 * np.polymul([1.0, 4.9, 12.25], [1.0, 4.9, 12.25]))
_W2_DEN = tuple(float(c) for c in np.polymul([1.0, 3.2, 4.0], [1.0, 3.2, 4.0]))


@dataclass(frozen=True)
class Weights:
    """W1 and W2 numerator/denominator coefficients; thesis values by default."""

    w1_num: tuple[float, ...] = _W1_NUM
    w1_den: tuple[float, ...] = _W1_DEN
    w2_num: tuple[float, ...] = _W2_NUM
    w2_den: tuple[float, ...] = _W2_DEN
    w2_extra_pole_rad_s: float | None = 10000.0

    def w1_magnitude(self, omega_rad_s) -> np.ndarray:
        s = 1j * np.asarray(omega_rad_s, dtype=float)
        return np.abs(np.polyval(self.w1_num, s) / np.polyval(self.w1_den, s))

    def w2_magnitude(self, omega_rad_s) -> np.ndarray:
        """``|W2(jw)|`` as the analysis uses it (:meth:`w2_for_design`: with the roll-off pole)."""
        num, den = self.w2_for_design()
        s = 1j * np.asarray(omega_rad_s, dtype=float)
        return np.abs(np.polyval(num, s) / np.polyval(den, s))

    def reference_frequency_rad_s(self) -> float:
        """The frequency scale of the control problem: half the geometric mean of W2's pole
        magnitudes (W2's nonzero poles, from its denominator's first and last coefficients).

        It scales exactly with the weights' time scale (``W(s) -> W(s/S)`` multiplies it by
        ``S``), so the analysis and the input design can work in normalised time and be
        scale-invariant. The factor 1/2 is a convention chosen so that the thesis's W2 (eq. 6.13,
        poles at 2 rad/s) gives exactly 1: the thesis examples are computed unnormalised, bit for
        bit as before. A W2 without dynamics gives 1.
        """
        den = np.trim_zeros(np.asarray(self.w2_den, dtype=float), "b")  # poles at s = 0 carry no scale
        degree = den.size - 1
        if degree < 1 or den[0] == 0.0:
            return 1.0
        return float(abs(den[-1] / den[0]) ** (1.0 / degree)) / 2.0

    def reference_magnitude(self) -> float:
        """The magnitude scale of the plant: ``|W1|`` at the reference frequency, relative to the
        thesis's ``|W1(j 1)|`` (W1 bounds the unmodelled dynamics in the plant's own units, so it
        scales with the receptance's unit). Exactly 1 for the thesis weights."""
        return float(self.w1_magnitude(self.reference_frequency_rad_s()) / _THESIS_W1_AT_1)

    def magnitude_scaled(self, factor: float) -> "Weights":
        """The weights of the plant ``factor G``: W1 (in plant units) times ``factor``, W2 unchanged."""
        return replace(self, w1_num=tuple(float(c) * float(factor) for c in self.w1_num))

    def time_scaled(self, factor: float) -> "Weights":
        """The weights of the time-scaled problem ``W'(s) = W(s / factor)`` (poles times ``factor``)."""
        f = float(factor)

        def poly(c):  # c(s/f) times f^degree(c): coefficient of s^(n-k) gets f^k
            c = np.asarray(c, dtype=float)
            return tuple(float(x) for x in c * f ** np.arange(c.size))

        def ratio(num, den):  # same rational function, denominator leading coefficient kept
            n, d = poly(num), poly(den)
            shift = f ** (len(den) - len(num))  # num(s/f)/den(s/f) = poly(num)/poly(den) * f^(deg den - deg num)
            return tuple(x * shift for x in n), d

        w1n, w1d = ratio(self.w1_num, self.w1_den)
        w2n, w2d = ratio(self.w2_num, self.w2_den)
        extra = None if not self.w2_extra_pole_rad_s else float(self.w2_extra_pole_rad_s) * f
        return Weights(w1n, w1d, w2n, w2d, extra)

    def w2_for_design(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """W2 with the extra roll-off pole (unit DC gain of the added factor ``p/(s+p)``)."""
        if not self.w2_extra_pole_rad_s:
            return self.w2_num, self.w2_den
        p = float(self.w2_extra_pole_rad_s)
        num = tuple(float(c) for c in p * np.asarray(self.w2_num, dtype=float))
        den = tuple(float(c) for c in np.polymul(self.w2_den, [1.0, p]))
        return num, den


THESIS_WEIGHTS = Weights()
_THESIS_W1_AT_1 = float(THESIS_WEIGHTS.w1_magnitude(1.0))
