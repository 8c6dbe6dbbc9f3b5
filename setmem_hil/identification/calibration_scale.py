"""The sensors' calibration as one unknown scale per output, not an error at every point (issue 26).

A force sensor's and a response sensor's sensitivities are known to their calibration
uncertainty (``calibration_uncertainty``, e.g. 1 % each) and do not change during a campaign:
every measured ratio of one output is ``c g(j omega)`` with the *same* unknown
``c = c_Y / c_F`` in ``[(1 - e_Y) / (1 + e_F), (1 + e_Y) / (1 - e_F)]``. Added to each point's
bound (as an independent error), 2 % of ``|g|`` near a resonance widens the pole intervals the
robust analysis is most sensitive to; the campaign through an 8-bit oscilloscope stalled at
mu-bar 1.09 on it.

Because the modal model (eq. 2.3) is linear in the residues and the scale leaves the poles alone,
the set-membership identification (chapter 3) can be run on the data as measured (the model of
``c G``: the same poles, residues ``c b``), and the plant's bounds follow exactly: ``b = b' / c``
over the scale's interval (:func:`plant_bounds`). The prior's residue bounds go the other way
(:func:`measured_scale_prior`). A choice of this project: the thesis's bounds are additive only.
Pure numerics.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from setmem_hil.model.modal_model import B0, B1, IntervalModel
from setmem_hil.model.prior import Prior

__all__ = ["ratio_scale", "plant_bounds", "measured_scale_prior", "UNIT_SCALE"]

UNIT_SCALE = (1.0, 1.0)


def ratio_scale(force_calibration: float, response_calibration: float) -> tuple[float, float]:
    """The interval of ``c = c_Y / c_F`` (measured ratio over true) for relative calibration
    uncertainties ``e_F`` and ``e_Y`` (each below 1)."""
    e_f, e_y = float(force_calibration), float(response_calibration)
    if not (0.0 <= e_f < 1.0 and 0.0 <= e_y < 1.0):
        raise ValueError(f"calibration uncertainties must be in [0, 1), found {e_f!r} and {e_y!r}")
    return (1.0 - e_y) / (1.0 + e_f), (1.0 + e_y) / (1.0 - e_f)


def _hull(lo: np.ndarray, hi: np.ndarray, factors: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """``{x f : lo <= x <= hi, f in [f_lo, f_hi]}`` (f > 0), elementwise; infinite ends stay."""
    with np.errstate(invalid="ignore"):
        ends = np.array([lo * factors[0], lo * factors[1], hi * factors[0], hi * factors[1]])
    ends = np.where(np.isnan(ends), 0.0, ends)  # 0 x inf: a zero scale never occurs (f > 0)
    return ends.min(axis=0), ends.max(axis=0)


def plant_bounds(model: IntervalModel, scale: tuple[float, float]) -> IntervalModel:
    """The plant's interval model from the model identified on data measured with ``scale``:
    the poles' bounds unchanged, every residue ``b' / c`` over the scale's interval."""
    if tuple(scale) == UNIT_SCALE:
        return model
    lo, hi = model.lower.copy(), model.upper.copy()
    for j in (B1, B0):
        lo[:, j], hi[:, j] = _hull(model.lower[:, j], model.upper[:, j], (1.0 / scale[1], 1.0 / scale[0]))
    return IntervalModel(lo, hi)


def measured_scale_prior(prior: Prior, scale: tuple[float, float]) -> Prior:
    """The prior of the model as measured (residue bounds times ``c`` over the scale's interval;
    a fixed ``b1 = 0`` stays fixed). Residual terms scale too."""
    if tuple(scale) == UNIT_SCALE:
        return prior

    def times(low: float, high: float) -> tuple[float, float]:
        a, b = _hull(np.array([low]), np.array([high]), scale)
        return float(a[0]), float(b[0])

    modes = []
    for m in prior.modes:
        b1 = times(m.b1_min, m.b1_max)
        b0 = times(m.b0_min, m.b0_max)
        modes.append(dataclasses.replace(m, b1_min=b1[0], b1_max=b1[1], b0_min=b0[0], b0_max=b0[1]))
    r = prior.residuals
    lower, upper = times(r.lower_min, r.lower_max), times(r.upper_min, r.upper_max)
    residuals = dataclasses.replace(r, lower_min=lower[0], lower_max=lower[1], upper_min=upper[0], upper_max=upper[1])
    return dataclasses.replace(prior, modes=tuple(modes), residuals=residuals)
