"""How much a lightly damped response will grow over a coming record (issue 26: ranging a scope).

A mode with decay rate ``sigma`` reaches its steady-state amplitude only after several
``1 / sigma`` (the beam's first mode: 100 s). A record ranged from a short levelling record
taken seconds after the drive came on sees the response still growing and clips: on an
oscilloscope that costs the whole record (it is refused, the channel moves up one step and the
record is taken again; a 120 s record near the first mode clipped up to seven times).

:func:`zero_state_response` is the structure's response from rest to a drive whose lines were
switched on, or changed level, at known times; :func:`predicted_peak` its largest value over a
coming record. The scope ranges each response channel for that peak plus what the last record
showed beyond this drive's predicted response then (an earlier record's mode still ringing):
:meth:`~setmem_hil.drivers.instruments.scope_rig.ScopeSensor._range_for_growth`. No I/O; the drive is

    f(t) = Re sum_k F_k e^{j omega_k t} x level(t),

``level(t)`` piecewise constant (``steps``: ``(t_j, level_j)``, the first the switch-on). For a
mode pair with poles ``p`` and residues ``R_p`` (``G(s) = sum_p R_p / (s - p)``) the zero-state
response to ``e^{j omega t}`` switched on at ``tau`` is

    G(j omega) e^{j omega t} - sum_p R_p e^{j omega tau} e^{p (t - tau)} / (j omega - p),   t >= tau,

and a level change is a switch-on of the difference.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from setmem_hil.model.modal_model import A0, A1, B0, B1, ModalParameters

__all__ = ["zero_state_response", "predicted_peak", "MAX_GRID_POINTS"]

MAX_GRID_POINTS = 20000  # per window: the peak of a long record of fast lines is sampled, not resolved
POINTS_PER_PERIOD = 16


def _poles_and_residues(model: ModalParameters) -> tuple[np.ndarray, np.ndarray]:
    """Every mode's two poles and their residues in ``G(s) = sum_p R_p / (s - p)``."""
    poles, residues = [], []
    for a1, a0, b1, b0 in model.values[:, [A1, A0, B1, B0]]:
        root = np.sqrt(complex(a1 * a1 - 4.0 * a0))
        if abs(root) < 1e-9 * max(1.0, math.sqrt(abs(a0))):  # a double pole: split it slightly
            root = complex(1e-9 * max(1.0, math.sqrt(abs(a0))))
        p1, p2 = (-a1 + root) / 2.0, (-a1 - root) / 2.0
        poles += [p1, p2]
        residues += [(b1 * p1 + b0) / (p1 - p2), (b1 * p2 + b0) / (p2 - p1)]
    return np.array(poles), np.array(residues)


def zero_state_response(model: ModalParameters, omegas_rad_s: Sequence[float], phasors: Sequence[complex],
                        steps: Sequence[tuple[float, float]], t_s: np.ndarray) -> np.ndarray:
    """The response at times ``t_s`` from rest to the drive of the module docstring (the
    model's modes; residual terms carry no transient and are left out)."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(omegas_rad_s, dtype=float)
    f = np.asarray(phasors, dtype=complex)
    p, r = _poles_and_residues(model)
    steady = (r[None, :] / (1j * w[:, None] - p[None, :]))  # (lines, poles): R_p / (j w - p)
    g = steady.sum(axis=1)  # G(j w) of the modes
    y = np.zeros(t.shape, dtype=complex)
    level = 0.0
    for tau, new_level in steps:
        change, level = new_level - level, new_level
        on = t >= tau
        if not change or not on.any():
            continue
        tt = t[on]
        forced = np.exp(1j * np.multiply.outer(tt, w)) @ (f * g)
        # transient: sum_k F_k e^{j w_k tau} sum_p steady[k, p] e^{p (t - tau)}
        coeff = (f * np.exp(1j * w * tau)) @ steady  # (poles,)
        free = np.exp(np.multiply.outer(tt - tau, p)) @ coeff
        y[on] += change * (forced - free)
    return y.real


def predicted_peak(model: ModalParameters, omegas_rad_s: Sequence[float], phasors: Sequence[complex],
                   steps: Sequence[tuple[float, float]], window: tuple[float, float]) -> float:
    """The largest ``|y|`` of :func:`zero_state_response` over ``window`` (sampled; nan when the
    model cannot say: residues not yet bounded)."""
    if not np.all(np.isfinite(model.values)) or not steps:
        return math.nan
    return _peak(model, omegas_rad_s, phasors, steps, window)


def _peak(model, omegas, phasors, steps, window: tuple[float, float]) -> float:
    t0, t1 = window
    n = int(min(MAX_GRID_POINTS, max(2, math.ceil((t1 - t0) * max(omegas) / (2 * math.pi) * POINTS_PER_PERIOD))))
    return float(np.max(np.abs(zero_state_response(model, omegas, phasors, steps, np.linspace(t0, t1, n)))))
