"""Lemmas 3.2-3.4 checked numerically: every piece of the chosen partition has a conservatism
ratio at most the target, at every frequency (dense grid), and fewer pieces would not do."""

import numpy as np
import pytest

from setmem_hil.identification.embedding import denominator_max, denominator_min
from setmem_hil.identification.partitioning import minimal_partition, partition_boxes, partition_is_feasible

OMEGA = np.geomspace(1e-2, 1e3, 20001)


def true_ratio(a0_lo, a0_hi, a1_lo, a1_hi):
    return np.max(denominator_max(OMEGA, a0_lo, a0_hi, a1_hi) / denominator_min(OMEGA, a0_lo, a0_hi, a1_lo))


def random_boxes(n, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        a0_lo = 10 ** rng.uniform(-1, 3)
        a0_hi = a0_lo * (1 + 10 ** rng.uniform(-3, -0.3))
        a1_hi = np.sqrt(a0_lo) * 10 ** rng.uniform(-2.5, -0.5)
        a1_lo = a1_hi * 10 ** rng.uniform(-1.5, 0)
        yield a0_lo, a0_hi, a1_lo, a1_hi


@pytest.mark.parametrize("delta", [1.05, 1.1, 1.3])
def test_every_piece_meets_the_target(delta):
    checked = 0
    for box in random_boxes(30, seed=int(delta * 100)):
        plan = minimal_partition(delta, *box, max_partitions=200)
        if plan is None:
            continue
        for piece in partition_boxes(plan, *box):
            assert true_ratio(*piece) <= delta * (1 + 1e-9)
            checked += 1
    assert checked > 20


def test_pieces_tile_the_box_geometrically():
    box = (39.0, 39.8, 0.1, 0.16)  # a beam mode-2 box after a few iterations
    plan = minimal_partition(1.1, *box, max_partitions=200)
    assert plan.count > 1
    pieces = partition_boxes(plan, *box)
    assert pieces[:, 0].min() == box[0] and pieces[:, 1].max() == box[1]
    assert pieces[:, 2].min() == box[2] and pieces[:, 3].max() == box[3]
    assert np.allclose(pieces[:, 1] / pieces[:, 0], (box[1] / box[0]) ** (1 / plan.n0))  # eq. (3.52)
    assert np.allclose(pieces[:, 3] / pieces[:, 2], (box[3] / box[2]) ** (1 / plan.n1))  # eq. (3.53)


def test_plan_is_minimal_and_monotone():
    for box in random_boxes(40, seed=7):
        plan = minimal_partition(1.1, *box, max_partitions=200)
        if plan is None:
            continue
        for n0 in range(1, plan.n0 + 1):
            for n1 in range(1, plan.n1 + 1):
                if n0 * n1 < plan.count:
                    assert not partition_is_feasible(n0, n1, 1.1, *box)
        # Corollary 3.1 item 3: more pieces stay feasible
        assert partition_is_feasible(plan.n0 + 1, plan.n1 + 1, 1.1, *box)


def test_no_partition_without_damping_lower_bound():
    assert minimal_partition(1.1, 0.8, 1.3, 0.0, 1.0, max_partitions=200) is None
