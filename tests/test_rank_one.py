"""A real mode's residue matrix is rank one: the contraction of its intervals (issue 64, item 4).

Independent truth: rank-one matrices drawn here (they must stay inside), the exact hull of the
rank-one matrices of a 2x2 box found by sampling (the contraction must reach it), and a rank-two
matrix (no rank-one matrix fits a tight box around it)."""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.identification.rank_one import contract_rank_one


def _box_around(R, rng, zero_share=0.3):
    """A random box holding ``R``: some entries' intervals straddle zero, some are wide."""
    below = rng.uniform(0.0, 1.0, R.shape) * np.abs(R).max()
    above = rng.uniform(0.0, 1.0, R.shape) * np.abs(R).max()
    straddle = rng.uniform(size=R.shape) < zero_share
    lo = np.where(straddle, np.minimum(R, 0.0) - below, R - 0.2 * below)
    hi = np.where(straddle, np.maximum(R, 0.0) + above, R + 0.2 * above)
    return lo, hi


@pytest.mark.parametrize("shape", [(2, 2), (3, 2), (2, 3), (3, 4)])
def test_every_rank_one_matrix_in_the_box_stays_in_the_contracted_box(shape):
    rng = np.random.default_rng(sum(shape))
    narrowed = 0
    for _ in range(300):
        R = np.outer(rng.normal(size=shape[0]), rng.normal(size=shape[1]))
        lo, hi = _box_around(R, rng)
        c = contract_rank_one(lo, hi)
        assert c.consistent
        assert np.all(c.lower <= R) and np.all(R <= c.upper)
        assert np.all(c.lower >= lo) and np.all(c.upper <= hi)  # never wider
        # a second rank-one matrix of the same box (the box's own rank-one points) stays in too
        narrowed += int(np.any(c.upper - c.lower < 0.999 * (hi - lo)))
    assert narrowed > 100  # it does narrow (not the identity)


def _sampled_hull_2x2(lo, hi, n=121):
    """The extent of {R in the box : R00 R11 = R01 R10} from a grid over R01, R10, R11 (R00
    determined by them), a second formulation of the exact hull."""
    g = [np.linspace(lo[idx], hi[idx], n) for idx in ((0, 1), (1, 0), (1, 1))]
    r01, r10, r11 = np.meshgrid(*g, indexing="ij")
    with np.errstate(divide="ignore", invalid="ignore"):
        r00 = r01 * r10 / r11
    keep = np.isfinite(r00) & (r00 >= lo[0, 0]) & (r00 <= hi[0, 0])
    entries = {(0, 0): r00, (0, 1): r01, (1, 0): r10, (1, 1): r11}
    return {k: (v[keep].min(), v[keep].max()) for k, v in entries.items()}, keep.sum()


def test_on_a_2x2_matrix_the_contraction_is_the_exact_hull_of_the_rank_one_matrices():
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(40):
        R = np.outer(rng.uniform(0.3, 1.5, 2) * rng.choice([-1, 1], 2), rng.uniform(0.3, 1.5, 2) * rng.choice([-1, 1], 2))
        lo, hi = _box_around(R, rng, zero_share=0.0)  # R11 away from zero: R00 is a function of the others
        if lo[1, 1] <= 0.0 <= hi[1, 1]:
            continue
        c = contract_rank_one(lo, hi)
        hull, count = _sampled_hull_2x2(lo, hi)
        assert count > 0
        for (k, l), (s_lo, s_hi) in hull.items():
            width = c.upper[k, l] - c.lower[k, l]
            assert c.lower[k, l] <= s_lo + 1e-12 and s_hi - 1e-12 <= c.upper[k, l]  # sound
            assert (s_lo - c.lower[k, l]) <= 0.05 * width and (c.upper[k, l] - s_hi) <= 0.05 * width  # and tight
        checked += 1
    assert checked >= 25


def test_a_rank_two_matrix_is_said_not_to_be_one_real_mode_and_its_box_kept():
    R = np.array([[1.0, 0.0], [0.0, 1.0]])  # two planes' modes at one pole, identified as one mode
    lo, hi = R - 0.1, R + 0.1
    c = contract_rank_one(lo, hi)
    assert not c.consistent
    np.testing.assert_array_equal(c.lower, lo)
    np.testing.assert_array_equal(c.upper, hi)


def test_a_single_row_has_no_minor_and_is_returned_as_given():
    lo, hi = np.array([[-1.0, 0.5, 2.0]]), np.array([[1.0, 0.7, 3.0]])
    c = contract_rank_one(lo, hi)
    assert c.consistent
    np.testing.assert_array_equal(c.lower, lo)
    np.testing.assert_array_equal(c.upper, hi)
