"""Frequency-response data with per-point error bounds (eq. 3.7: ``|n(j omega)| <= R(omega)``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from setmem_hil.model.experiment import Measurement


MAX_MAGNITUDE = 1e150
"""Largest |omega|, |G| or bound accepted: squares and products stay finite in double precision."""


@dataclass(frozen=True)
class FrequencyData:
    """Measured ``g(j omega_i)`` with absolute error bounds ``R_i``; arrays of equal length."""

    omega_rad_s: np.ndarray
    response: np.ndarray
    bound: np.ndarray

    def __post_init__(self):
        w = np.atleast_1d(np.asarray(self.omega_rad_s, dtype=float))
        g = np.atleast_1d(np.asarray(self.response, dtype=complex))
        r = np.atleast_1d(np.asarray(self.bound, dtype=float))
        if not (w.shape == g.shape == r.shape) or w.ndim != 1:
            raise ValueError(f"omega, response, bound: expected equal 1-D shapes, found {w.shape}, {g.shape}, {r.shape}")
        if np.any(~np.isfinite(w)) or np.any(w <= 0):
            raise ValueError("omega_rad_s: expected finite positive frequencies")
        if np.any(~np.isfinite(g)):
            raise ValueError("response: expected finite values")
        if np.any(~np.isfinite(r)) or np.any(r < 0):
            raise ValueError("bound: expected finite non-negative bounds")
        if max(np.max(w, initial=0.0), np.max(np.abs(g), initial=0.0), np.max(r, initial=0.0)) > MAX_MAGNITUDE:
            raise ValueError(f"omega, response, bound: values beyond {MAX_MAGNITUDE:g} (the identification squares "
                             "frequencies and responses; such values overflow; check the units)")
        object.__setattr__(self, "omega_rad_s", w)
        object.__setattr__(self, "response", g)
        object.__setattr__(self, "bound", r)

    def __len__(self) -> int:
        return self.omega_rad_s.size

    def to_frd(self):
        """The points as a python-control ``FrequencyResponseData`` (rad/s), sorted by
        frequency (python-control interpolates between neighbours); the bounds are not part of it."""
        import control

        order = np.argsort(self.omega_rad_s, kind="stable")
        return control.frd(self.response[order], self.omega_rad_s[order])

    @classmethod
    def from_measurements(cls, measurements: Iterable[Measurement], output: int = 0) -> "FrequencyData":
        """The measurements' data; ``output`` k >= 1 takes the k-th of their other sensors
        (``Measurement.others``, issue 25) instead of the control output."""
        ms = list(measurements)
        if output == 0:
            response, bound = [m.response for m in ms], [m.bound for m in ms]
        else:
            response, bound = [m.others[output - 1][0] for m in ms], [m.others[output - 1][1] for m in ms]
        return cls(
            np.array([m.omega_rad_s for m in ms], dtype=float),
            np.array(response, dtype=complex),
            np.array(bound, dtype=float),
        )

    def measurements(self) -> list[Measurement]:
        return [Measurement(float(w), complex(g), float(r)) for w, g, r in zip(self.omega_rad_s, self.response, self.bound)]

    def sorted_by_frequency(self) -> "FrequencyData":
        """The same points in ascending frequency (a stable sort: equal frequencies keep their order)."""
        return self.subset(np.argsort(self.omega_rad_s, kind="stable"))

    def subset(self, index) -> "FrequencyData":
        return FrequencyData(self.omega_rad_s[index], self.response[index], self.bound[index])

    def appended(self, other: "FrequencyData") -> "FrequencyData":
        return FrequencyData(
            np.concatenate([self.omega_rad_s, other.omega_rad_s]),
            np.concatenate([self.response, other.response]),
            np.concatenate([self.bound, other.bound]),
        )
