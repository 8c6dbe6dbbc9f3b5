"""The union of a partition's certified bounds, solving only the objectives that can move it.

Algorithm 3.2 (thesis section 3.2.3) bounds every free parameter over each box of the ``(a0, a1)``
partition and keeps the union: the smallest lower and the largest upper bound over the boxes not
proved empty. Solving every objective on every box costs ``2 p`` conic solves per box.

A box's certified bound on a *partitioned* parameter never lies beyond the box's own edge (a
lower bound of ``a0`` over a box is at least the box's ``a0_lo``; ``bound_box`` clamps it there).
So once some box has given the union a lower bound ``v`` of ``a0``, a box whose own ``a0_lo`` is
above ``v`` cannot lower it, and its ``a0``-minimisation is not solved. Solving each partitioned
objective over the boxes in the order of their own edge (the lowest ``a0_lo`` first for the
minimum, and so on) leaves, on a grid of ``n0 x n1`` boxes, about one row or column of solves per
objective instead of every box.

Two phases keep everything else as it was:

1. every box with its first objective (the old feasibility test: the first free parameter's
   minimum) and every objective of a parameter that is not partitioned (the residues: a box's
   bound on them is not limited by its edges);
2. each remaining objective of ``a1`` and ``a0`` over the boxes phase 1 left feasible, in the order
   of their edge, skipping a box that cannot change the union.

The union's bounds are the same as solving everything: a skipped objective's box bound lies
inside the union already. The solver's points (``argmin`` / ``argmax``) are too: ties between
boxes go to the box that comes first in the partition's order, as when every box was solved in
that order. What can differ: a box that only a skipped objective would have proved empty stays in
the union (its residue bounds still valid, at most wider), and an uncertified skipped objective is
no longer reported (its box bound did not decide anything). A box proved empty in phase 2 leaves
the union, which is then recomputed without it (results already solved are reused).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PartitionUnion", "partition_union"]


@dataclass
class PartitionUnion:
    """The union over a partition's boxes (module docstring); ``feasible``: the indices of the
    boxes not proved empty; ``certificates``: those of the boxes proved empty."""

    lower: np.ndarray
    upper: np.ndarray
    argmin: np.ndarray
    argmax: np.ndarray
    feasible: list[int]
    certificates: list = field(default_factory=list)
    unverified: list[str] = field(default_factory=list)
    n_skipped: int = 0  # objectives not solved because they could not move the union


def partition_union(problem, boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]], free: np.ndarray,
                    partitioned: tuple[int, ...]) -> PartitionUnion:
    """Bounds of every free parameter over the union of ``boxes`` (``(C, box_lo, box_hi)`` each:
    the points' bounds over that box and its edges), by ``problem.bound_box``; ``partitioned``:
    the parameters whose range the boxes split (module docstring)."""
    n = free.size
    every = [(int(p), sign) for p in np.flatnonzero(free) for sign in (1.0, -1.0)]
    if not every:
        raise ValueError("partition_union: no free parameter")
    first = every[0]
    phase_one = [first] + [o for o in every[1:] if o[0] not in partitioned]
    phase_two = [o for o in every[1:] if o[0] in partitioned]
    solved: dict[tuple[int, tuple[int, float]], object] = {}  # (box, objective) -> BoxSolution
    union = PartitionUnion(np.full(n, np.inf), np.full(n, -np.inf), np.full((n, n), np.nan), np.full((n, n), np.nan), [])
    empty: set[int] = set()

    for b, (C, lo, hi) in enumerate(boxes):
        sol = problem.bound_box(C, lo, hi, objectives=phase_one)
        if not sol.feasible:
            empty.add(b)
            union.certificates.append(sol.certificate)
            continue
        for objective in phase_one:
            solved[(b, objective)] = sol
    while True:
        union.lower[:], union.upper[:] = np.inf, -np.inf
        union.argmin[:], union.argmax[:] = np.nan, np.nan
        winners: dict[tuple[int, float], int] = {}
        feasible = [b for b in range(len(boxes)) if b not in empty]
        for objective in phase_one:
            for b in feasible:
                _take(union, winners, objective, b, solved[(b, objective)])
        found_empty = False
        skipped = 0
        for objective in phase_two:
            p, sign = objective
            edge = (lambda b: boxes[b][1][p]) if sign > 0 else (lambda b: -boxes[b][2][p])
            for b in sorted(feasible, key=lambda b: (edge(b), b)):  # a box found empty ends the pass
                if not _may_move(union, winners, objective, b, edge(b)):
                    skipped += 1
                    continue
                if (b, objective) not in solved:
                    C, lo, hi = boxes[b]
                    sol = problem.bound_box(C, lo, hi, objectives=[objective])
                    if not sol.feasible:
                        empty.add(b)
                        union.certificates.append(sol.certificate)
                        found_empty = True
                        break
                    solved[(b, objective)] = sol
                _take(union, winners, objective, b, solved[(b, objective)])
            if found_empty:
                break
        if not found_empty:
            union.n_skipped = skipped
            break
    union.feasible = [b for b in range(len(boxes)) if b not in empty]
    union.unverified = _unverified(union.feasible, solved)
    if union.feasible:  # a fixed parameter's bound is its value (the boxes hold it)
        fixed = ~free
        union.lower[fixed] = boxes[union.feasible[0]][1][fixed]
        union.upper[fixed] = boxes[union.feasible[0]][2][fixed]
    return union


def _take(union: PartitionUnion, winners: dict, objective: tuple[int, float], b: int, sol) -> None:
    """Box ``b``'s bound for ``objective`` into the union; a tie goes to the earlier box."""
    p, sign = objective
    if sign > 0:
        value, best = sol.lower[p], union.lower[p]
        if value < best or (value == best and b < winners.get(objective, b)):
            union.lower[p], union.argmin[p], winners[objective] = value, sol.argmin[p], b
    else:
        value, best = sol.upper[p], union.upper[p]
        if value > best or (value == best and b < winners.get(objective, b)):
            union.upper[p], union.argmax[p], winners[objective] = value, sol.argmax[p], b


def _may_move(union: PartitionUnion, winners: dict, objective: tuple[int, float], b: int, edge: float) -> bool:
    """Can box ``b`` (its own edge ``edge``, negated for an upper bound) change the union's bound
    or win a tie?"""
    p, sign = objective
    best = union.lower[p] if sign > 0 else -union.upper[p]
    return edge < best or (edge == best and b < winners.get(objective, b + 1))


def _unverified(feasible: list[int], solved: dict) -> list[str]:
    """The feasible boxes' uncertified bounds, each solve once (a box's phase-one solve answers
    several objectives), box by box in the partition's order."""
    kept, seen, out = set(feasible), set(), []
    for (box, _), sol in sorted(solved.items(), key=lambda item: (item[0][0], item[0][1][0], -item[0][1][1])):
        if box in kept and id(sol) not in seen:
            seen.add(id(sol))
            out.extend(sol.unverified)
    return out
