"""The union of a partition's certified bounds with the pole objectives pruned
(:mod:`setmem_hil.identification.partition_union`).

Second formulation: every objective solved on every box and the union taken in the partition's
order (Algorithm 3.2 as it was written before the pruning). The pruned union must give the same
bounds, the same solver points at them and the same feasible boxes, with fewer solves.
"""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.identification.embedding import embedding_bound
from setmem_hil.identification.one_mode_solver import OneModeProblem
from setmem_hil.identification.partition_union import partition_union
from setmem_hil.identification.partitioning import PartitionPlan, partition_boxes
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import A0, A1, ModalParameters
from setmem_hil.sim_backends.noise import bounded_complex_noise


def _one_mode_case(seed: int, b1_free: bool):
    """One lightly damped mode (a0 = 25, zeta 0.01) seen at 9 points near its peak, its noise
    inside the bound; the pass's box around it, partitioned 6 x 5."""
    rng = np.random.default_rng(seed)
    truth = ModalParameters.from_modal([5.0], [0.01], [3.0], [0.2 if b1_free else 0.0])
    w = 5.0 * (1 + 0.01 * np.linspace(-2.5, 2.5, 9)) * rng.uniform(0.998, 1.002, 9)
    bound = np.full(w.size, 0.3 * np.max(np.abs(truth.frequency_response(w))))
    data = FrequencyData(w, truth.frequency_response(w) + bounded_complex_noise(bound, rng), bound)
    lo = np.array([0.03, 24.0, -1.0 if b1_free else 0.0, 0.0])  # a1 > 0: geometric partition edges
    hi = np.array([0.3, 26.0, 1.0 if b1_free else 0.0, 10.0])
    return data, lo, hi


def _boxes(data, lo, hi, plan):
    out = []
    for a0_lo, a0_hi, a1_lo, a1_hi in partition_boxes(plan, lo[A0], hi[A0], lo[A1], hi[A1]):
        box_lo, box_hi = lo.copy(), hi.copy()
        box_lo[A0], box_hi[A0], box_lo[A1], box_hi[A1] = a0_lo, a0_hi, a1_lo, a1_hi
        out.append((embedding_bound(data.omega_rad_s, data.bound, a0_lo, a0_hi, a1_hi), box_lo, box_hi))
    return out


def _every_objective_union(problem, boxes):
    """Every objective on every box, the union in the partition's order (a strict improvement wins)."""
    n = boxes[0][1].size
    lower, upper = np.full(n, np.inf), np.full(n, -np.inf)
    argmin, argmax = np.full((n, n), np.nan), np.full((n, n), np.nan)
    feasible = []
    for b, (C, box_lo, box_hi) in enumerate(boxes):
        sol = problem.bound_box(C, box_lo, box_hi)
        if not sol.feasible:
            continue
        feasible.append(b)
        for p in range(n):
            if sol.lower[p] < lower[p]:
                lower[p], argmin[p] = sol.lower[p], sol.argmin[p]
            if sol.upper[p] > upper[p]:
                upper[p], argmax[p] = sol.upper[p], sol.argmax[p]
    return lower, upper, argmin, argmax, feasible


@pytest.mark.parametrize("seed, b1_free", [(1, False), (2, False), (3, True)])
def test_the_pruned_union_is_the_union_of_every_objective_with_fewer_solves(seed, b1_free):
    data, lo, hi = _one_mode_case(seed, b1_free)
    boxes = _boxes(data, lo, hi, PartitionPlan(6, 5))
    reference = OneModeProblem(data.omega_rad_s, data.response, lo, hi)
    lower, upper, argmin, argmax, feasible = _every_objective_union(reference, boxes)
    pruned = OneModeProblem(data.omega_rad_s, data.response, lo, hi)
    union = partition_union(pruned, boxes, np.asarray(pruned.free, dtype=bool), (A1, A0))
    assert union.feasible == feasible and len(feasible) >= 3  # several boxes hold part of the set
    np.testing.assert_array_equal(union.lower, lower)
    np.testing.assert_array_equal(union.upper, upper)
    free = np.asarray(pruned.free, dtype=bool)
    np.testing.assert_array_equal(union.argmin[free], argmin[free])
    np.testing.assert_array_equal(union.argmax[free], argmax[free])
    assert union.n_skipped > 0 and pruned.n_solves < reference.n_solves
