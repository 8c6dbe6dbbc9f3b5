"""Partitioning the a-priori box of ``(a0, a1)`` to bound the embedding's conservatism
(thesis Lemmas 3.2-3.4, eq. 3.31-3.61, Corollary 3.1).

Splitting ``[a0_lo, a0_hi]`` into ``n0`` and ``[a1_lo, a1_hi]`` into ``n1`` geometric pieces
(constant upper/lower ratio, eq. 3.51-3.53) guarantees a ratio of conservatism at most
``delta`` (our ``gamma`` target) at every frequency when eq. (3.48)-(3.50) hold. We choose the
feasible ``(n0, n1)`` with the fewest partitions ``n0 n1`` by a search that uses the
monotonicity of Corollary 3.1 (feasibility is monotone in each of n0, n1).
Assumption 3.1 (``a1_lo > 0``) is needed; with ``a1_lo = 0`` no finite partition exists.

Correction to Lemma 3.3. Its proof says the inequalities bind in the partition with the
largest a1 (``k1 = n1``) and smallest a0 (``k0 = 1``). But by Lemma 3.4 both sides of
(3.54)-(3.55) are non-positive, so the left side ``a1_hi,k^2 (1 - delta^2 / eps1^2)`` is largest
(least negative) for the *smallest* a1 piece, and the right side ``2 a0_lo,k f(eps0)`` is smallest
(most negative) for the *largest* a0 piece. We therefore check Lemma 3.2 in the piece
``a1 in [a1_lo, a1_lo eps1]``, ``a0 in [a0_hi / eps0, a0_hi]``, which makes the guarantee hold in
every piece (verified numerically in ``tests/test_partitioning.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def _lemma_rhs(delta: float, r: float) -> tuple[float, float]:
    """Right-hand sides of eq. (3.54)-(3.55) per unit ``2 a0_lo``, with ``r = eps0``."""
    d2 = delta * delta
    s = math.sqrt(d2 - 1.0)
    rhs1 = s * math.sqrt(max(d2 - r * r, 0.0)) - (d2 - r)
    rhs2 = s * math.sqrt(max(r * r * d2 - 1.0, 0.0)) - (r * d2 - 1.0)
    return rhs1, rhs2


def partition_is_feasible(n0: int, n1: int, delta: float, a0_lo: float, a0_hi: float, a1_lo: float, a1_hi: float) -> bool:
    """Eq. (3.48)-(3.50), corrected (module docstring): does an ``n0 x n1`` geometric partition
    guarantee a conservatism ratio ``<= delta`` in every piece?"""
    if delta <= 1.0 or a1_lo <= 0.0 or a0_lo <= 0.0:
        return False
    eps0 = (a0_hi / a0_lo) ** (1.0 / n0)
    eps1 = (a1_hi / a1_lo) ** (1.0 / n1)
    if delta < eps0:  # eq. (3.50)
        return False
    # binding piece: a1 in [a1_lo, a1_lo eps1] (left side), a0 in [a0_hi / eps0, a0_hi] (right side)
    lhs = (a1_lo * eps1) ** 2 * (1.0 - (delta / eps1) ** 2)
    rhs1, rhs2 = _lemma_rhs(delta, eps0)
    a0_piece_lo = a0_hi / eps0
    return lhs <= 2.0 * a0_piece_lo * rhs1 and lhs <= 2.0 * a0_piece_lo * rhs2


@dataclass(frozen=True)
class PartitionPlan:
    """Number of geometric pieces in a0 and a1 (``(1, 1)`` means no partitioning)."""

    n0: int
    n1: int

    @property
    def count(self) -> int:
        return self.n0 * self.n1


def minimal_partition(delta: float, a0_lo: float, a0_hi: float, a1_lo: float, a1_hi: float, max_partitions: int) -> PartitionPlan | None:
    """Fewest ``n0 n1 <= max_partitions`` satisfying eq. (3.48)-(3.50), or ``None``.

    For each ``n1`` the smallest feasible ``n0`` is found by bisection (feasibility is monotone
    in ``n0``, Corollary 3.1 item 3); the product is minimised over ``n1``.
    """
    if a1_lo <= 0.0 or delta <= 1.0:
        return None
    best: PartitionPlan | None = None
    for n1 in range(1, max_partitions + 1):
        n0_cap = max_partitions // n1
        if n0_cap < 1:
            break
        if not partition_is_feasible(n0_cap, n1, delta, a0_lo, a0_hi, a1_lo, a1_hi):
            continue
        lo, hi = 1, n0_cap
        while lo < hi:
            mid = (lo + hi) // 2
            if partition_is_feasible(mid, n1, delta, a0_lo, a0_hi, a1_lo, a1_hi):
                hi = mid
            else:
                lo = mid + 1
        if best is None or lo * n1 < best.count:
            best = PartitionPlan(lo, n1)
    return best


def geometric_edges(lo: float, hi: float, n: int) -> np.ndarray:
    """``n + 1`` edges with constant ratio between consecutive pieces (eq. 3.52-3.53)."""
    if n == 1 or lo <= 0.0:
        return np.array([lo, hi])
    edges = lo * (hi / lo) ** (np.arange(n + 1) / n)
    edges[0], edges[-1] = lo, hi
    return edges


def partition_boxes(plan: PartitionPlan, a0_lo: float, a0_hi: float, a1_lo: float, a1_hi: float) -> np.ndarray:
    """Boxes ``(a0_lo, a0_hi, a1_lo, a1_hi)`` of every partition, shape ``(n0 n1, 4)``."""
    e0 = geometric_edges(a0_lo, a0_hi, plan.n0)
    e1 = geometric_edges(a1_lo, a1_hi, plan.n1)
    boxes = [(e0[i], e0[i + 1], e1[k], e1[k + 1]) for i in range(plan.n0) for k in range(plan.n1)]
    return np.array(boxes, dtype=float)
