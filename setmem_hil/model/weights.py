"""Control-design weights (thesis eq. 6.1 and 6.13), as transfer-function coefficients.

``W1`` bounds the additive unmodelled dynamics; ``W2`` weights the sensitivity (robust
performance: ``|W2 S| <= 1``). For the H2 design ``W2`` gets an extra pole at
``s = -w2_extra_pole_rad_s`` (default 10000) so that its D term vanishes (section 6.3.1).
Coefficients are highest power first (``numpy.polyval`` order).
"""

from __future__ import annotations

from dataclasses import dataclass

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

    def w2_for_design(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """W2 with the extra roll-off pole (unit DC gain of the added factor ``p/(s+p)``)."""
        if not self.w2_extra_pole_rad_s:
            return self.w2_num, self.w2_den
        p = float(self.w2_extra_pole_rad_s)
        num = tuple(float(c) for c in p * np.asarray(self.w2_num, dtype=float))
        den = tuple(float(c) for c in np.polymul(self.w2_den, [1.0, p]))
        return num, den


THESIS_WEIGHTS = Weights()
