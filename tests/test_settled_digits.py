"""Inputs cut to fixed digits (numerics/settled_digits): a box is only ever widened, by at most two
units of its last kept digit, and inputs that differ by rounding alone come out the same."""

from __future__ import annotations

import numpy as np

from setmem_hil.numerics.settled_digits import cut_nearest, cut_outwards


def test_the_cut_box_holds_the_box_and_is_barely_wider():
    rng = np.random.default_rng(0)
    lo = rng.uniform(-1, 1, 2000) * 10.0 ** rng.integers(-8, 8, 2000)
    hi = lo + np.abs(lo) * 10.0 ** rng.uniform(-6, 0, 2000)
    c_lo, c_hi = cut_outwards(lo, hi, digits=10)
    assert np.all(c_lo <= lo) and np.all(c_hi >= hi)
    assert np.all(lo - c_lo <= 2.0e-9 * np.abs(lo) * 1.000001) and np.all(c_hi - hi <= 2.0e-9 * np.abs(hi) * 1.000001)


def test_rounding_differences_and_round_numbers_land_in_one_cell():
    round_numbers = np.array([392.4361, 10.0, 1.0, 0.1, 100.0, 0.95 ** 2, 1e-3, 2.5, 16.0, 1185921.0])
    for x in round_numbers:
        for y in (x * (1 + 2e-16), x * (1 - 2e-16), np.nextafter(x, 0), np.nextafter(x, np.inf), x * (1 + 1e-13)):
            assert cut_outwards(x, x)[0] == cut_outwards(y, y)[0], (x, y)
            assert cut_outwards(x, x)[1] == cut_outwards(y, y)[1], (x, y)
            assert cut_nearest(x) == cut_nearest(y), (x, y)
    rng = np.random.default_rng(1)
    x = rng.uniform(0.5, 500.0, 20000)
    y = x * (1 + rng.uniform(-1e-14, 1e-14, x.size))
    same = np.mean((cut_outwards(x, x)[0] == cut_outwards(y, y)[0]) & (cut_outwards(x, x)[1] == cut_outwards(y, y)[1]))
    assert same > 0.999


def test_zeros_and_infinities_are_kept():
    lo, hi = cut_outwards(np.array([0.0, -np.inf, 3.0]), np.array([0.0, 1.0, np.inf]))
    assert lo[0] == 0.0 and hi[0] == 0.0 and lo[1] == -np.inf and hi[2] == np.inf
    assert cut_nearest(0.0) == 0.0
