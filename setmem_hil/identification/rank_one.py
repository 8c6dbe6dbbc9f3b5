"""A real mode's residue matrix is rank one: its intervals contracted by that alone (issue 64, item 4).

A structure's mode ``i`` with a real (normal) shape enters the FRF matrix as
``psi_i phi_i^T / (s^2 + a1_i s + a0_i)``: its residue matrix ``B0_i = psi_i phi_i^T`` (sensors x
exciters) has rank one (thesis appendix A; ``b1 = 0``). So every 2x2 minor vanishes:

    B0[k, l] * B0[m, n] = B0[k, n] * B0[m, l]        (k != m, l != n)

and an entry is the product of two others over a fourth, wherever that fourth cannot be zero:

    B0[k, l] in B0[k, n] * B0[m, l] / B0[m, n]       (0 not in B0[m, n])

:func:`contract_rank_one` intersects every entry's interval with every such quotient (interval
arithmetic rounded outward), again until nothing narrows by more than a relative ``1e-12``. Every
rank-one matrix inside the box stays inside: the contraction is as guaranteed as the box, under one
assumption, that the mode's shape is real (our choice: it is applied only where the prior fixes
``b1 = 0``; a complex mode is rank one in its complex residue, not in ``b0`` and ``b1`` apart).

On a 2x2 matrix there is one minor, each entry appears in it once, and the fixed point is the
exact hull of the rank-one matrices in the box (tested against sampling). On larger matrices the
minors share entries and the hull can be wider than the exact set's; it is never narrower.

What it buys: a pair that sees a mode poorly (an exciter near the mode's node, a pair never
measured) is bounded by the pairs that see it well. An interval emptied by the contraction means
no rank-one matrix fits the box: the mode is not one real mode (a repeated pole identified as one
mode, a complex mode, an inconsistency); the box is then returned as it was, and said so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RankOneContraction", "contract_rank_one"]

_RELATIVE_STEP = 1e-12
_MAX_SWEEPS = 50


@dataclass(frozen=True)
class RankOneContraction:
    """The contracted intervals (``consistent``) or the given ones unchanged (not ``consistent``:
    no rank-one matrix lies in the box), and the number of sweeps over the minors."""

    lower: np.ndarray
    upper: np.ndarray
    consistent: bool
    sweeps: int


def _outward(lo: np.ndarray | float, hi: np.ndarray | float) -> tuple[float, float]:
    return float(np.nextafter(lo, -np.inf)), float(np.nextafter(hi, np.inf))


def _times(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    products = (a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1])
    return _outward(min(products), max(products))


def _over(a: tuple[float, float], d: tuple[float, float]) -> tuple[float, float] | None:
    """``a / d`` for an interval ``d`` that excludes zero (None when it does not)."""
    if d[0] <= 0.0 <= d[1]:
        return None
    quotients = (a[0] / d[0], a[0] / d[1], a[1] / d[0], a[1] / d[1])
    return _outward(min(quotients), max(quotients))


def contract_rank_one(lower: np.ndarray, upper: np.ndarray) -> RankOneContraction:
    """Every entry of the interval matrix ``[lower, upper]`` (sensors x exciters) narrowed to the
    products-over-quotients of its 2x2 minors (module docstring); a row or column of one entry
    has no minor and is returned as given."""
    lo, hi = np.array(lower, dtype=float), np.array(upper, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 2:
        raise ValueError("the residue matrix's bounds must be two (sensors x exciters) arrays of one shape")
    n_rows, n_cols = lo.shape
    for sweep in range(1, _MAX_SWEEPS + 1):
        narrowed = False
        for k in range(n_rows):
            for l in range(n_cols):
                for m in range(n_rows):
                    for n in range(n_cols):
                        if m == k or n == l:
                            continue
                        quotient = _over(_times((lo[k, n], hi[k, n]), (lo[m, l], hi[m, l])), (lo[m, n], hi[m, n]))
                        if quotient is None:
                            continue
                        new_lo, new_hi = max(lo[k, l], quotient[0]), min(hi[k, l], quotient[1])
                        if new_lo > new_hi:
                            return RankOneContraction(np.array(lower, dtype=float), np.array(upper, dtype=float), False, sweep)
                        scale = max(abs(lo[k, l]), abs(hi[k, l]), np.finfo(float).tiny)
                        if (new_lo - lo[k, l]) > _RELATIVE_STEP * scale or (hi[k, l] - new_hi) > _RELATIVE_STEP * scale:
                            narrowed = True
                        lo[k, l], hi[k, l] = new_lo, new_hi
        if not narrowed:
            return RankOneContraction(lo, hi, True, sweep)
    return RankOneContraction(lo, hi, True, _MAX_SWEEPS)
