"""The lifted form of a close pair and its McCormick envelopes (issue 47), held against truth
computed another way:

- the lifted residual, with each product variable set to the product it stands for, against the
  multiplied constraint evaluated directly from the model's definition (no expansion);
- the conic program's certified bounds against points sampled in the box that satisfy the
  multiplied constraint (every one must lie inside), and an empty box proved empty only where a
  dense sample finds no such point;
- the witnesses (points said to fit) against the model evaluated directly.
"""

import numpy as np

from setmem_hil.identification.certified_cone_program import AffineConeProgram
from setmem_hil.identification.feasible_points import chebyshev_fit, pulled_back
from setmem_hil.identification.mode_group import lifted_pair
from setmem_hil.sim_backends.close_pair import close_pair_case


def _multiplied(x, w, g):
    """``g D1 D2 - N1 D2 - N2 D1`` from the definition ``D = s^2 + a1 s + a0``, ``N = b1 s + b0``."""
    s = 1j * w
    (a1, a0, b1, b0), (c1, c0, d1, d0) = np.asarray(x).reshape(2, 4)
    D1, D2 = s * s + a1 * s + a0, s * s + c1 * s + c0
    return g * D1 * D2 - (b1 * s + b0) * D2 - (d1 * s + d0) * D1


def _products(x, lo, hi, pairs):
    y = (x - 0.5 * (lo + hi)) / (0.5 * (hi - lo))
    return np.array([y[p] * y[q] for p, q in pairs])


def _pair_data(separation=0.01):
    truth, data, _ = close_pair_case(separation, n=120)
    pair = truth.values[:2].reshape(-1)
    # the third mode subtracted exactly: the pair's data with the data's bound
    third = truth.values[2]
    s = 1j * data.omega_rad_s
    g = data.response - (third[2] * s + third[3]) / (s * s + third[0] * s + third[1])
    return pair, data.omega_rad_s, g, data.bound


def test_the_lifted_residual_is_the_multiplied_constraint_exactly():
    pair, w, g, _ = _pair_data()
    rng = np.random.default_rng(3)
    lo = pair - np.array([0.05, 3.0, 0.05, 2.0, 0.05, 3.0, 0.05, 2.0])
    hi = pair + np.array([0.2, 1.0, 0.02, 1.0, 0.1, 2.0, 0.03, 3.0])
    r_c, J, err, scale, products = lifted_pair(w, g, lo, hi)
    assert products.K.shape[1] == len(products.pairs) == 12  # a x a, b1 x a, a x b2: no b x b product
    c = 0.5 * (lo + hi)
    for _ in range(50):
        x = lo + (hi - lo) * rng.uniform(size=8)
        lifted = r_c + J @ (x - c) + products.K @ _products(x, lo, hi, products.pairs)
        direct = _multiplied(x, w, g)
        assert np.all(np.abs(lifted - direct) <= err + 1e-12 * np.abs(direct))
    # the bound's factor is the box's largest |D1| |D2| (eq. 3.34 twice), checked on a grid of corners
    s = 1j * w
    corners = [np.abs(s * s + a1 * s + a0) for a1 in (lo[0], hi[0]) for a0 in (lo[1], hi[1])]
    corners2 = [np.abs(s * s + a1 * s + a0) for a1 in (lo[4], hi[4]) for a0 in (lo[5], hi[5])]
    assert np.all(scale >= np.max(corners, axis=0) * np.max(corners2, axis=0) * (1 - 1e-12))


def _program(w, g, E, lo, hi):
    r_c, J, err, scale, products = lifted_pair(w, g, lo, hi)
    return AffineConeProgram(r_c, J, err, lo, hi, w, products), scale * E


def test_certified_bounds_of_the_lifted_program_hold_every_sampled_point_that_satisfies_it():
    pair, w, g, E = _pair_data(0.03)
    lo = pair - np.array([0.02, 0.4, 0.02, 0.3, 0.02, 0.4, 0.02, 0.3])
    hi = pair + np.array([0.02, 0.4, 0.02, 0.3, 0.02, 0.4, 0.02, 0.3])
    program, C = _program(w, g, E, lo, hi)
    sol = program.bound_box(C, lo, hi)
    assert sol.feasible and not sol.unverified
    assert np.all(sol.lower <= pair) and np.all(pair <= sol.upper)
    assert np.any(sol.upper - sol.lower < 0.9 * (hi - lo))  # it narrows something
    # points of the set near its edge: along random directions from the truth (which satisfies the
    # constraint: the data are within their bound of it), bisected to the last satisfying point
    rng = np.random.default_rng(5)

    def satisfies(x):
        return bool(np.all(x >= lo) and np.all(x <= hi) and np.all(np.abs(_multiplied(x, w, g)) <= C))

    assert satisfies(pair)
    reach = np.zeros(8)
    for _ in range(300):
        d = (hi - lo) * rng.standard_normal(8)
        a, b = 0.0, 1.0
        for _ in range(40):
            a, b = ((a + b) / 2, b) if satisfies(pair + (a + b) / 2 * d) else (a, (a + b) / 2)
        x = pair + a * d
        assert np.all(sol.lower <= x) and np.all(x <= sol.upper)
        reach = np.maximum(reach, np.abs(x - pair))
    assert np.all(reach > 0)


def test_a_box_the_lifted_program_calls_empty_holds_no_point_that_satisfies_the_constraint():
    pair, w, g, E = _pair_data(0.01)
    # the pair's a0 swapped in order: mode 1 held 3 % above mode 2's truth
    lo = pair.copy()
    lo[[0, 1, 4, 5]] = (0.0, 104.0, 0.0, 98.0)
    hi = lo.copy()
    hi[[0, 1, 4, 5]] = (0.5, 106.0, 0.5, 99.0)
    lo[[2, 3, 6, 7]], hi[[2, 3, 6, 7]] = (-0.1, -10.0, -0.1, -10.0), (0.1, 10.0, 0.1, 10.0)
    program, C = _program(w, g, E, lo, hi)
    assert not program.bound_box(C, lo, hi).feasible
    rng = np.random.default_rng(2)
    for _ in range(3000):
        x = lo + (hi - lo) * rng.uniform(size=8)
        assert not np.all(np.abs(_multiplied(x, w, g)) <= C)


def test_witnesses_fit_every_point_when_the_model_is_evaluated_directly():
    truth, data, prior = close_pair_case(0.01, n=200)
    box = prior.initial_bounds()
    lo, hi = box.lower.reshape(-1), box.upper.reshape(-1)
    start = truth.values.reshape(-1) * (1 + 0.002 * np.array([1, 1, 0, 1] * 3))  # off the truth
    x, f = chebyshev_fit(data.omega_rad_s, data.response, data.bound, lo, hi, start)

    def direct_misfit(v):
        s = 1j * data.omega_rad_s
        G = sum((b1 * s + b0) / (s * s + a1 * s + a0) for a1, a0, b1, b0 in v.reshape(-1, 4))
        return np.max(np.abs(data.response - G) / data.bound)

    assert direct_misfit(start) > 1.0 >= f
    assert abs(direct_misfit(x) - f) < 1e-9
    far = x + 0.01 * np.abs(x)
    back = pulled_back(far, x, data.omega_rad_s, data.response, data.bound)
    assert back is None or direct_misfit(back) <= 1.0
