"""A structure seen by several exciters and several sensors (issue 64; thesis appendix A).

Every input-output pair shares the structure's poles; mode ``i``'s residue in the response of
sensor ``k`` to exciter ``l`` is its shape at the sensor times its shape at the exciter (a
structure's mode, ``R_i = psi_i phi_i^T``, rank one):

    G_kl(s) = sum_i psi_ik phi_il (b1_i s + b0_i) / (s^2 + a1_i s + a0_i)

``modes`` holds ``(a1, a0, b1, b0)`` per mode with the residue of unit shapes; ``shape_out``
(``psi``, one column per sensor) and ``shape_in`` (``phi``, one column per exciter) scale it. With
one exciter and one sensor of shape 1 this is :class:`ModalParameters` itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.model.modal_model import B0, B1, ModalParameters

__all__ = ["ModalMatrix"]


@dataclass(frozen=True)
class ModalMatrix:
    """Shared poles, rank-one residue matrices (module docstring)."""

    modes: ModalParameters
    shape_out: np.ndarray  # (n_modes, n_sensors): psi
    shape_in: np.ndarray  # (n_modes, n_exciters): phi
    sensors: tuple[str, ...]
    exciters: tuple[str, ...]

    def __post_init__(self):
        n = self.modes.n_modes
        out, inp = np.asarray(self.shape_out, dtype=float), np.asarray(self.shape_in, dtype=float)
        if out.shape != (n, len(self.sensors)) or inp.shape != (n, len(self.exciters)):
            raise ValueError(f"shapes: expected ({n}, {len(self.sensors)}) at the sensors and ({n}, {len(self.exciters)}) at the "
                             f"exciters, found {out.shape} and {inp.shape}")
        if not (np.all(np.isfinite(out)) and np.all(np.isfinite(inp))):
            raise ValueError("shapes: every value finite")
        object.__setattr__(self, "shape_out", out)
        object.__setattr__(self, "shape_in", inp)

    @property
    def n_modes(self) -> int:
        return self.modes.n_modes

    def residue_factor(self, sensor: int, exciter: int) -> np.ndarray:
        """``psi_ik phi_il`` per mode: what the pair's residues are of the unit-shape ones."""
        return self.shape_out[:, sensor] * self.shape_in[:, exciter]

    def pair(self, sensor: int, exciter: int) -> ModalParameters:
        """The modal model of one input-output pair (the shared poles, that pair's residues)."""
        values = np.array(self.modes.values, dtype=float)
        factor = self.residue_factor(sensor, exciter)
        values[:, B1] *= factor
        values[:, B0] *= factor
        return ModalParameters(values)

    def frequency_response(self, omega_rad_s) -> np.ndarray:
        """``G(j omega)``, shape ``(len(omega), n_sensors, n_exciters)``."""
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
        per_mode = self.modes.mode_responses(w)  # (n_modes, len(w)): unit shapes
        return np.einsum("iw,ik,il->wkl", per_mode, self.shape_out, self.shape_in)
