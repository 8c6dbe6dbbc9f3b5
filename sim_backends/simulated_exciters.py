"""A simulated structure driven by several exciters and read by several sensors (issue 64).

``measure(exciter, omega)`` is one dwell: the named exciter drives, every sensor is read, and each
reading is ``G_kl(j omega)`` plus complex noise strictly inside its bound (the column ``l`` of the
FRF matrix, :class:`~setmem_hil.model.modal_matrix.ModalMatrix`).

The noise belongs to the sensor, not to the pair: a sensor's bound is the thesis's noise shape
(section 6.2: the response with every pole and zero at damping 1) of the largest response that
sensor sees, every mode's residue ``|psi_ik| max_l |phi_il| |b0_i|`` (the strongest exciter for
each mode). So a pair that barely sees a mode (an exciter near that mode's node) reads it under
the same noise as the pair that sees it well, as on a rig; that is why a second exciter helps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from setmem_hil.model.experiment import Measurement
from setmem_hil.model.modal_matrix import ModalMatrix
from setmem_hil.model.modal_model import B0, B1, ModalParameters
from setmem_hil.sim_backends.noise import bounded_complex_noise, noise_bound_function

__all__ = ["SimulatedExcitersExperiment"]


@dataclass
class SimulatedExcitersExperiment:
    """The FRF matrix of ``truth``, one column per dwell, with bounded noise per sensor."""

    truth: ModalMatrix
    noise_profile: str = "fully_damped"
    noise_scale: float = 1.0
    seed: int = 0
    n_measured: int = 0
    _bounds: list = field(init=False, repr=False)

    def __post_init__(self):
        self._bounds = [noise_bound_function(self.noise_profile, self._seen_by(k), self.noise_scale)
                        for k in range(len(self.truth.sensors))]

    def _seen_by(self, sensor: int) -> ModalParameters:
        """The largest response sensor ``sensor`` sees: each mode from its strongest exciter."""
        values = np.array(self.truth.modes.values, dtype=float)
        factor = np.abs(self.truth.shape_out[:, sensor]) * np.max(np.abs(self.truth.shape_in), axis=1)
        values[:, B0] = np.abs(values[:, B0]) * factor
        values[:, B1] = values[:, B1] * factor
        return ModalParameters(values)

    def noise_bound(self, sensor: int, omega_rad_s) -> np.ndarray:
        return np.asarray(self._bounds[sensor](np.atleast_1d(np.asarray(omega_rad_s, dtype=float))), dtype=float)

    def measure(self, exciter: int, omega_rad_s: float) -> tuple[Measurement, ...]:
        """One dwell of ``exciter`` at ``omega_rad_s``: every sensor's reading, in the truth's sensor order."""
        if not 0 <= int(exciter) < len(self.truth.exciters):
            raise ValueError(f"exciter: expected an index into {list(self.truth.exciters)}, found {exciter!r}")
        rng = np.random.default_rng([int(self.seed), int(self.n_measured)])  # one stream per dwell: resumable
        self.n_measured += 1
        g = self.truth.frequency_response([omega_rad_s])[0, :, int(exciter)]
        out = []
        for k in range(len(self.truth.sensors)):
            bound = float(self.noise_bound(k, omega_rad_s)[0])
            out.append(Measurement(float(omega_rad_s), complex(g[k] + bounded_complex_noise(np.array([bound]), rng)[0]), bound))
        return tuple(out)

    def close(self) -> None:  # nothing to release
        pass
