"""Certified interval bounds of one mode's parameters by conic programming (Problem 3.2), Clarabel.

Each data point is a 3-dimensional second-order cone ``(C_j, Re(r_j), Im(r_j))`` with
``r_j = g_j (-w_j^2 + a1 j w_j + a0) - (b1 j w_j + b0)`` (eq. 3.26, affine form of
:mod:`setmem_hil.identification.embedding`); the partition's box on every free parameter is a
nonnegative cone. Bounding every free parameter from above and below is ``2 p`` linear
objectives over the same feasible set: one Clarabel solver per pass, re-solved with
``update(q=...)`` across objectives and ``update(b=...)`` across partitions.

The program's normalisation, its certified bounds (weak duality, checked Farkas certificates)
and the translation of the solver's status are those of every affine cone program:
:mod:`setmem_hil.identification.certified_cone_program`.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.identification.certified_cone_program import (  # noqa: F401  (re-exported names)
    CERT_GAP, PRIMAL_INFEASIBLE, SOLVED, AffineConeProgram, BoxSolution, _tight_settings,
)

_EPS = np.finfo(float).eps


def parameter_count(n_outputs: int) -> int:
    """Length of one mode's parameter vector ``(a1, a0, b1_1, b0_1, ..., b1_K, b0_K)``."""
    return 2 + 2 * int(n_outputs)


class OneModeProblem(AffineConeProgram):
    """The normalised SOC program of one mode for fixed data, reusable across boxes and objectives.

    Several outputs (issue 25): the poles ``(a1, a0)`` are shared and each output ``k`` has its
    own residues ``(b1_k, b0_k)``; a point of output ``k`` is the cone of eq. (3.26) on
    ``(a1, a0, b1_k, b0_k)``. One output is exactly the problem of the thesis, parameter order
    ``(a1, a0, b1, b0)``.

    Parameters
    ----------
    omega_rad_s, g : arrays
        Data points used (points with infinite error bound must be removed beforehand).
    box_lo, box_hi : arrays of shape (2 + 2K,)
        The pass's outer box of ``(a1, a0, b1_1, b0_1, ...)``; parameters with ``lo == hi`` are
        fixed. Every box later given to :meth:`bound_box` must lie inside it.
    output : array of int, optional
        The output (0-based) of each point; default all 0 (one output).
    """

    def __init__(self, omega_rad_s, g, box_lo, box_hi, output=None):
        w = np.asarray(omega_rad_s, dtype=float)
        g = np.asarray(g, dtype=complex)
        box_lo = np.asarray(box_lo, dtype=float)
        box_hi = np.asarray(box_hi, dtype=float)
        n_params = box_lo.size
        if n_params < 4 or n_params % 2 or box_hi.size != n_params:
            raise ValueError(f"box_lo, box_hi: expected equal lengths 2 + 2K, found {box_lo.size} and {box_hi.size}")
        out = np.zeros(w.size, dtype=int) if output is None else np.asarray(output, dtype=int)
        b1_col, b0_col = 2 + 2 * out, 3 + 2 * out  # each point's residue columns
        c, _ = self.box_centre(box_lo, box_hi)
        jw = 1j * w
        # residual at the centre, written to limit cancellation near resonance: g (a0 - w^2) + ...
        r_c = g * ((c[1] - w * w) + jw * c[0]) - (jw * c[b1_col] + c[b0_col])
        rows = np.arange(w.size)
        J = np.zeros((w.size, n_params), dtype=complex)
        J[:, 0], J[:, 1] = jw * g, g
        J[rows, b1_col], J[rows, b0_col] = -jw, -1.0
        # absolute rounding error of the formed data: r_c carries the cancellation of
        # (a0 - w^2) near resonance, bounded by a few ulps of its largest term
        ag = np.abs(g)
        err_rc = 8 * _EPS * (ag * (np.abs(c[1]) + w * w + w * np.abs(c[0])) + w * np.abs(c[b1_col]) + np.abs(c[b0_col]))
        self._setup(r_c, J, err_rc, box_lo, box_hi, w)

