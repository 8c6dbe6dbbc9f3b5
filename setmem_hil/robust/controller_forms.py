"""The compensator in the forms a real-time target takes: poles, zeros and gain, the discrete
state space (Tustin, prewarped) and second-order sections.

Pure numerics on a SISO python-control ``StateSpace`` in rad/s with the feedback sign of thesis
6.3.2, footnote 3 (positive feedback, ``u = K y``). python-control does the state space, its
evaluation and the prewarped Tustin map (``sample_system(..., "bilinear", prewarp_frequency=)``);
this module adds what it lacks: zeros, poles and gain by eigenvalue problems, and sections. No transfer-function polynomials anywhere:
for the lightly damped compensators of this problem (poles a few 1e-3 from the imaginary axis,
orders 10-20) the polynomial coefficients lose the poles; every form here comes from the state
space by eigenvalue problems.

* zeros: the finite generalized eigenvalues of the Rosenbrock pencil
  ``([[A, B], [C, D]], [[I, 0], [0, 0]])``; poles: ``eig(A)``; gain: the response at a point away
  from both divided by the product form there;
* Tustin with prewarping at ``w_p`` (python-control's): ``s = (w_p / tan(w_p Ts / 2)) (z - 1) / (z + 1)``,
  so the discrete response equals the continuous one exactly at ``w_p`` (the mu-bar peak: where
  the guarantee is tightest);
* sections: ``scipy.signal.zpk2sos`` of the discrete zeros, poles and gain, the gain folded into
  the first section.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg
import scipy.signal

__all__ = ["statespace_from_lists", "ZerosPolesGain", "zpk_of", "tustin_prewarped", "second_order_sections", "frequency_response"]


def statespace_from_lists(doc: dict, Ts: float = 0.0) -> control.StateSpace:
    """A ``control.StateSpace`` from ``{"A": [[...]], "B": ..., "C": ..., "D": ...}`` (the
    journal's and the controller file's lists); ``Ts`` 0: continuous time."""
    A = np.asarray(doc["A"], dtype=float).reshape(len(doc["A"]), -1) if len(doc["A"]) else np.zeros((0, 0))
    n = A.shape[0]
    B = np.asarray(doc["B"], dtype=float).reshape(n, -1) if n else np.zeros((0, 1))
    C = np.asarray(doc["C"], dtype=float).reshape(-1, n) if n else np.zeros((1, 0))
    return control.ss(A, B, C, np.asarray(doc["D"], dtype=float).reshape(C.shape[0], B.shape[1]), Ts)


@dataclass(frozen=True)
class ZerosPolesGain:
    zeros: np.ndarray
    poles: np.ndarray
    gain: float


def frequency_response(sys: control.StateSpace, omega_rad_s: np.ndarray) -> np.ndarray:
    """``C (x I - A)^-1 B + D`` at ``x = j w`` (continuous) or ``exp(j w Ts)`` (discrete): python-control's evaluation."""
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    return np.asarray(control.frequency_response(sys, w).complex, dtype=complex).reshape(w.size)


def _response_at(sys: control.StateSpace, x: complex) -> complex:
    n = sys.nstates
    return complex((sys.C @ np.linalg.solve(x * np.eye(n) - sys.A, sys.B) + sys.D)[0, 0]) if n else complex(sys.D[0, 0])


def zpk_of(sys: control.StateSpace) -> ZerosPolesGain:
    """Zeros (finite transmission zeros), poles and gain of a SISO state space."""
    n = sys.nstates
    poles = np.linalg.eigvals(sys.A) if n else np.zeros(0, complex)
    pencil = np.block([[sys.A, sys.B], [sys.C, sys.D]])
    mass = np.zeros_like(pencil)
    mass[:n, :n] = np.eye(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        values = scipy.linalg.eigvals(pencil, mass) if n else np.zeros(0, complex)
    zeros = values[np.isfinite(values)] if values.size else values
    zeros = zeros[np.abs(zeros) < 1e12 * max(1.0, float(np.max(np.abs(poles), initial=1.0)))]
    # the gain: the response at a point away from every zero and pole, over the product form there
    scale = max(1.0, float(np.max(np.abs(np.concatenate([poles, zeros])), initial=1.0)))
    if sys.dt:
        x = 0.3 + 0.4j  # inside the unit circle, off the real axis: away from poles of a stable loop
    else:
        x = scale * (1.7 + 2.3j)
    product = np.prod(x - zeros) / np.prod(x - poles)
    gain = _response_at(sys, x) / product
    return ZerosPolesGain(zeros, poles, float(gain.real))


def tustin_prewarped(sys: control.StateSpace, fs_hz: float, prewarp_rad_s: float) -> control.StateSpace:
    """The discrete compensator at sample rate ``fs_hz`` (Tustin, exact at ``prewarp_rad_s``):
    python-control's ``sample_system``, after checking the prewarp lies below the Nyquist frequency."""
    if not 0 < prewarp_rad_s < math.pi * fs_hz:
        raise ValueError(f"prewarp frequency {prewarp_rad_s:.6g} rad/s must lie below the Nyquist frequency "
                         f"{math.pi * fs_hz:.6g} rad/s (--fs {fs_hz:g} Hz)")
    return control.sample_system(sys, 1.0 / fs_hz, "bilinear", prewarp_frequency=prewarp_rad_s)


def second_order_sections(continuous: control.StateSpace, fs_hz: float, prewarp_rad_s: float) -> tuple[np.ndarray, float]:
    """``(sos, gain)`` of the prewarped Tustin image: rows ``[b0, b1, b2, 1, a1, a2]``.

    The continuous zeros, poles and gain (:func:`zpk_of`) go through the bilinear map in product
    form (``scipy.signal.bilinear_zpk`` at the prewarped rate); the zeros of the discrete state
    space would do too, but the generalized eigenvalues of a pencil whose poles crowd at ``z = 1``
    lose digits the continuous ones keep. The gain is folded into the first section (scipy's
    convention), so ``gain`` is 1.0 and ``sosfilt(sos, x)`` is the compensator's output.
    """
    Ts = 1.0 / fs_hz
    fs_warped = prewarp_rad_s / (2.0 * math.tan(prewarp_rad_s * Ts / 2.0))
    z = zpk_of(continuous)
    zd, pd, kd = scipy.signal.bilinear_zpk(z.zeros, z.poles, z.gain, fs_warped)
    return scipy.signal.zpk2sos(zd, pd, kd, pairing="nearest"), 1.0
