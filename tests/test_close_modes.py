"""Closely spaced modes identified together (issue 47), held against independent truth:

- the relaxations' remainder bounds against the model evaluated directly at sampled parameters,
  their Jacobians against finite differences;
- the identified intervals against the true parameters, against the linearised exact feasible set
  (a linear program in HiGHS, not the identification's conic programs) and against a local
  nonlinear optimiser (SLSQP) searching the exact set's extremes, which must never leave the box.
"""

import numpy as np
import pytest
from scipy.optimize import minimize

from setmem_hil.identification.algorithm import identify
from setmem_hil.identification.exact_set import linearised_extent, model_jacobian
from setmem_hil.identification.mode_group import close_groups, linearised_group, multiplied_group, second_order_group
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.sim_backends.close_pair import close_pair_case


def _direct(x, w, g):
    """``g - G(x)`` and the multiplied form, evaluated directly from the definition."""
    s = 1j * w
    modes = np.asarray(x).reshape(-1, 4)
    D = [s * s + a1 * s + a0 for a1, a0, _, _ in modes]
    N = [b1 * s + b0 for _, _, b1, b0 in modes]
    return g - sum(n / d for n, d in zip(N, D)), g * D[0] * D[1] - N[0] * D[1] - N[1] * D[0]


def test_remainder_bounds_hold_at_sampled_parameters_and_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    w = np.linspace(9.0, 11.0, 60)
    g = rng.normal(size=60) + 1j * rng.normal(size=60)
    lo = np.array([0.05, 99.0, -0.1, 3.0, 0.08, 102.0, -0.1, -3.0])
    hi = np.array([0.15, 101.0, 0.1, 5.0, 0.12, 104.0, 0.1, -2.0])
    c = 0.5 * (lo + hi)
    r_c, J_div, _, rho_div = linearised_group(w, g, lo, hi)
    P_c, J_mul, _, rho_mul, _ = multiplied_group(w, g, lo, hi)
    assert np.allclose(r_c, _direct(c, w, g)[0]) and np.allclose(P_c, _direct(c, w, g)[1])
    for k in range(8):
        step = np.zeros(8)
        step[k] = 1e-6 * max(1.0, abs(c[k]))
        fd = [(_direct(c + step, w, g)[f] - _direct(c - step, w, g)[f]) / (2 * step[k]) for f in (0, 1)]
        # the divided form drops a mode's pole terms where its disc form is used (near resonance)
        used = J_div[:, k] != 0
        assert used.sum() > 10
        assert np.allclose(fd[0][used], J_div[used, k], rtol=1e-5, atol=1e-7 * np.abs(J_div).max())
        assert np.allclose(fd[1], J_mul[:, k], rtol=1e-5, atol=1e-7 * np.abs(J_mul).max())
    worst_div = worst_mul = 0.0
    usable = np.isfinite(rho_div)
    for _ in range(3000):
        x = lo + (hi - lo) * rng.uniform(size=8)
        div, mul = _direct(x, w, g)
        worst_div = max(worst_div, np.max(np.abs(div - r_c - J_div @ (x - c))[usable] / rho_div[usable]))
        worst_mul = max(worst_mul, np.max(np.abs(mul - P_c - J_mul @ (x - c)) / rho_mul))
    assert worst_div <= 1.0 and worst_mul <= 1.0
    assert worst_div > 0.3 and worst_mul > 0.3  # and not loose by orders of magnitude


def test_the_second_order_form_holds_at_sampled_parameters_and_its_products_are_the_mixed_derivatives():
    """Against the model evaluated directly: the residual at any parameter of the box (corners
    included) is the form's affine part plus its products ``y_p y_q`` within the remainder bound;
    the products' coefficients are the residual's mixed second derivatives at the centre (finite
    differences); away from a pair's resonance its remainder is far below the mean-value form's."""
    rng = np.random.default_rng(3)
    w = np.concatenate([np.linspace(8.0, 12.0, 40), np.linspace(25.0, 35.0, 40)])
    g = rng.normal(size=w.size) + 1j * rng.normal(size=w.size)
    lo = np.array([0.05, 99.0, -0.1, 2.0, 0.05, 100.0, -0.1, 1.0, 0.28, 955.0, -0.01, 2.9])
    hi = np.array([0.25, 101.0, 0.1, 8.0, 0.45, 103.0, 0.1, 7.0, 0.32, 965.0, 0.01, 3.1])
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    r_c, J, _, rho, products = second_order_group(w, g, lo, hi)
    assert np.allclose(r_c, _direct3(c, w, g))
    assert {(int(p) % 4, int(q) % 4) for p, q in products.pairs} == {(3, 1), (3, 0), (2, 1), (2, 0)}
    assert all(int(p) // 4 == int(q) // 4 for p, q in products.pairs)  # a mode's own products only
    for k, (p, q) in enumerate(products.pairs):
        used = products.K[:, k] != 0
        e_p, e_q = np.eye(12)[p] * 1e-3 * h[p], np.eye(12)[q] * 1e-3 * h[q]
        mixed = (_direct3(c + e_p + e_q, w, g) - _direct3(c + e_p - e_q, w, g) - _direct3(c - e_p + e_q, w, g)
                 + _direct3(c - e_p - e_q, w, g)) / (4e-6)  # per unit of y_p y_q
        assert np.allclose(mixed[used], products.K[used, k], rtol=1e-3, atol=1e-6 * np.abs(products.K[:, k]).max())
    usable = np.isfinite(rho)
    worst = 0.0
    for trial in range(3000):
        y = rng.uniform(-1.0, 1.0, size=12) if trial % 2 else rng.choice([-1.0, 1.0], size=12)
        z = np.array([y[p] * y[q] for p, q in products.pairs])
        gap = np.abs(_direct3(c + h * y, w, g) - r_c - J @ (h * y) - products.K @ z)
        worst = max(worst, np.max(gap[usable] / rho[usable]))
    assert 0.3 < worst <= 1.0
    far = w > 20.0  # the pair's remainder at the far mode's lines: n d is its first-order part
    pair_second, pair_first = second_order_group(w, g, lo[:8], hi[:8])[3], linearised_group(w, g, lo[:8], hi[:8])[3]
    assert np.all(pair_second[far] < 0.1 * pair_first[far])


def _direct3(x, w, g):
    """``g - G(x)`` evaluated from the definition, any number of modes."""
    s = 1j * w
    return g - sum((b1 * s + b0) / (s * s + a1 * s + a0) for a1, a0, b1, b0 in np.asarray(x).reshape(-1, 4))


def test_separated_modes_are_never_grouped_and_close_ones_are():
    centres = np.array([1.0, 6.3, 17.6])
    owner = np.repeat([0, 1, 2], 4)
    huge = np.full((3, 12), 10.0)
    zeta = np.full(3, 0.05)
    assert close_groups(huge, np.ones(12), owner, centres, zeta) == []  # mismatch alone does not group far modes
    centres = np.array([10.0, 10.3, 31.0])
    assert close_groups(huge, np.ones(12), owner, centres, zeta) == [(0, 1)]
    assert close_groups(np.full((3, 12), 0.5), np.ones(12), owner, centres, zeta) == []  # the split narrows: alone
    # the hammer test's 810 and 851 Hz: 5 % apart, 4.4 of its prior's bandwidths: alone
    assert close_groups(huge[:2, :8], np.ones(8), owner[:8], np.array([810.0, 851.0]), np.full(2, 0.0114)) == []


@pytest.mark.parametrize("centres, want", [
    ([100.0, 103.0, 103.6, 106.0], [(1, 2)]),  # the plate's case: a close pair in the middle of a linked chain
    ([100.0, 100.5, 103.0, 103.4], [(0, 1), (2, 3)]),  # two pairs: each kept whole
    ([100.0, 100.4, 103.0, 106.0, 106.3], [(0, 1), (3, 4)]),  # the middle mode alone, its neighbours' pairs closer
    ([103.6, 100.0, 106.0, 103.0], [(0, 3)]),  # not given in frequency order: 103.0 and 103.6 are the pair
])
def test_a_chain_of_linked_modes_is_grouped_closest_pair_first(centres, want):
    """Issue 62 item 3: grouping by closeness, not by order. Every neighbour linked (mismatch above
    the bound everywhere, all within the overlap distance); groups of two: the closest pairs win.
    Truth: the pairs written down from the centres by hand."""
    n = len(centres)
    owner = np.repeat(np.arange(n), 4)
    groups = close_groups(np.full((n, 4 * n), 10.0), np.ones(4 * n), owner, np.array(centres), np.full(n, 0.05))
    assert groups == want


def _nonlinear_extreme(data, x0, lower, upper, p, sign):
    """SLSQP from the truth towards one parameter's extreme of the exact feasible set."""
    free = (upper > lower).reshape(-1)
    scale = np.maximum(np.abs(x0[free]), 1e-3)

    def full(u):
        x = x0.copy()
        x[free] = x0[free] + u * scale
        return x

    def fit(u):
        G, _ = model_jacobian(full(u), data.omega_rad_s)
        return 1.0 - np.abs(data.response - G) / data.bound

    k = list(np.flatnonzero(free)).index(p)
    res = minimize(lambda u: sign * u[k], np.zeros(free.sum()), constraints=[{"type": "ineq", "fun": fit}],
                   method="SLSQP", options={"maxiter": 300, "ftol": 1e-14})
    return full(res.x)[p], float(np.min(fit(res.x)))


@pytest.mark.slow
@pytest.mark.parametrize("separation", [0.10, 0.03, 0.01])
def test_a_close_pair_is_bounded_within_1_5x_of_the_exact_set_and_holds_every_fitting_parameter(separation):
    truth, data, prior = close_pair_case(separation)
    result = identify(data, prior)
    box = prior.initial_bounds()
    assert result.groups and set(result.groups[0]) >= {0, 1}
    assert result.verified.all()
    assert result.model.contains(truth).all()
    ex_lo, ex_hi = linearised_extent(data.omega_rad_s, data.response, data.bound, truth.values, box.lower, box.upper)
    ratio = result.model.width / (ex_hi - ex_lo)
    assert np.all(ratio[:, [0, 1, 3]] < 1.5), ratio  # a1, a0, b0 of every mode (b1 below)
    assert np.all(ratio[:, 2] < 1.5), ratio
    doc = result.to_document()
    assert doc["modes"][0]["group"] == doc["modes"][1]["group"] and 1 in doc["modes"][0]["group"]
    # the exact set's extremes found by a local nonlinear search never leave the guaranteed box
    x0 = truth.values.reshape(-1)
    lo, hi = result.model.lower.reshape(-1), result.model.upper.reshape(-1)
    for p in (1, 3, 5, 7):  # a0 and b0 of the pair
        for sign in (1.0, -1.0):
            value, fit = _nonlinear_extreme(data, x0, box.lower.reshape(-1), box.upper.reshape(-1), p, sign)
            if fit >= -1e-9:  # a point of the exact set
                assert lo[p] - 1e-9 * abs(lo[p]) <= value <= hi[p] + 1e-9 * abs(hi[p])


@pytest.mark.slow
@pytest.mark.parametrize("residues", [(4.0, -2.5), (4.0, 2.5)], ids=["opposite", "same"])
def test_the_far_mode_of_a_1_percent_pair_at_five_times_the_noise_is_not_held_by_the_pairs_mismatch(monkeypatch, residues):
    """The far mode (31 rad/s) beside a 1 % pair at five times the noise: the split bounds it by the
    pair's whole worst-case mismatch (4.4x the exact set with every mode contracted together in the
    multiplied form); with the pair's residues kept as variables at its points (the mixed form) it
    comes within 2x of the linearised exact set and holds the truth, and since stop 58 every
    interval of every mode within 1.5x; since stop 59 (the polish cuts the grouped modes'
    parameters) with same-sign residues too. Every group search's answer
    lies in the box it was given (the second round's reached 1e143 when a certified bound beyond a
    box was kept as its bound, stop 55)."""
    from setmem_hil.identification import algorithm

    real, outside = algorithm.identify_group, []

    def checked(w, g, E, lo, hi, settings, pieces=()):
        found = real(w, g, E, lo, hi, settings, pieces)
        if not (np.all(found.lower >= lo) and np.all(found.upper <= hi)):
            outside.append((found.lower, found.upper))
        return found

    monkeypatch.setattr(algorithm, "identify_group", checked)
    truth, data, prior = close_pair_case(0.01, residues=residues, noise=5.0)
    result = identify(data, prior)
    assert not outside, outside
    box = prior.initial_bounds()
    assert result.model.contains(truth).all() and result.verified.all()
    ex_lo, ex_hi = linearised_extent(data.omega_rad_s, data.response, data.bound, truth.values, box.lower, box.upper)
    ratio = result.model.width / (ex_hi - ex_lo)
    assert np.all(ratio[2] < 2.0), ratio
    # stop 58 (the divided form only within a tenth of the bound; the polish from the pair's
    # leaves): every interval of every mode within the 1.5x (stop 59: 1.43 / 1.43 / 1.28
    # opposite, 1.17 / 1.17 / 1.42 same-sign)
    assert np.all(ratio < 1.5), ratio


@pytest.mark.slow  # 16 s; the grouped path of the same pair stays in the default tier
def test_the_one_mode_split_alone_stays_at_the_prior_for_a_3_percent_pair():
    """The failure the issue measured, kept as the reason for the groups (chapter 3's path)."""
    from setmem_hil.identification.algorithm import IdentifySettings

    truth, data, prior = close_pair_case(0.03)
    alone = identify(data, prior, settings=IdentifySettings(groups=False))
    box = prior.initial_bounds()
    ex_lo, ex_hi = linearised_extent(data.omega_rad_s, data.response, data.bound, truth.values, box.lower, box.upper)
    assert np.max(alone.model.width[:2, 1] / (ex_hi - ex_lo)[:2, 1]) > 50


def test_a_group_inconsistent_with_its_prior_is_exit_3_material():
    from setmem_hil.errors import InconsistentDataError

    _, data, prior = close_pair_case(0.10)
    # the conjugate response is that of negatively damped modes: no a1 >= 0 fits it
    with pytest.raises(InconsistentDataError):
        identify(FrequencyData(data.omega_rad_s, np.conj(data.response), data.bound), prior)


def test_a_groups_bounds_do_not_depend_on_the_threads(monkeypatch):
    """The same data give the same bounds whatever the number of workers and their timing (two
    runs of the 1 % pair once disagreed: the threads' best-first queue took boxes in the order they
    finished); each box's contraction here is delayed at random; and the truth stays inside."""
    import random
    import time

    from setmem_hil.identification import mode_group
    from setmem_hil.identification.mode_group import GroupSettings, identify_group
    from setmem_hil.model.modal_model import ModalParameters

    contract, jitter = mode_group._Search.contract, random.Random(5)

    def late_contract(self, lo, hi):
        time.sleep(jitter.uniform(0.0, 0.02))
        return contract(self, lo, hi)

    monkeypatch.setattr(mode_group._Search, "contract", late_contract)
    truth, data, prior = close_pair_case(0.01, n=100)
    far = ModalParameters(truth.values[2:])
    g = data.response - far.frequency_response(data.omega_rad_s)
    box = prior.initial_bounds()
    runs = [identify_group(data.omega_rad_s, g, data.bound, box.lower[:2], box.upper[:2],
                           GroupSettings(max_boxes=16, workers=workers)) for workers in (1, 3)]
    for run in runs[1:]:
        assert np.array_equal(run.lower, runs[0].lower) and np.array_equal(run.upper, runs[0].upper)
        assert run.boxes == runs[0].boxes and run.n_solves == runs[0].n_solves
    assert np.all(runs[0].lower <= truth.values[:2]) and np.all(truth.values[:2] <= runs[0].upper)


def test_contracting_the_open_boxes_at_the_budget_only_narrows_and_keeps_every_fitting_point():
    """``contract_at_budget`` (the final all-modes contraction's): a search cut short after a few
    boxes gives a box inside the one the open boxes kept as they stood, and strictly narrower
    somewhere; both hold the truth and points checked to fit every line (an independent local
    search, :func:`feasible_points.fitting_extent`, from the truth)."""
    from setmem_hil.identification.feasible_points import fitting_extent
    from setmem_hil.identification.mode_group import GroupSettings, identify_group
    from setmem_hil.model.modal_model import ModalParameters

    truth, data, prior = close_pair_case(0.01, n=100)
    far = ModalParameters(truth.values[2:])
    g = data.response - far.frequency_response(data.omega_rad_s)
    box = prior.initial_bounds()
    lo, hi = box.lower[:2], box.upper[:2]
    kept, contracted = (identify_group(data.omega_rad_s, g, data.bound, lo, hi,
                                       GroupSettings(max_boxes=6, contract_at_budget=flag, subset_stage=False))
                        for flag in (False, True))
    assert kept.exhausted and contracted.exhausted
    assert np.all(contracted.lower >= kept.lower) and np.all(contracted.upper <= kept.upper)
    assert np.any(contracted.upper - contracted.lower < 0.9 * (kept.upper - kept.lower))
    inner_lo, inner_hi = fitting_extent(data.omega_rad_s, g, data.bound, lo.reshape(-1), hi.reshape(-1), truth.values[:2].reshape(-1))
    for result in (kept, contracted):
        assert np.all(result.lower.reshape(-1) <= np.minimum(inner_lo, truth.values[:2].reshape(-1)))
        assert np.all(result.upper.reshape(-1) >= np.maximum(inner_hi, truth.values[:2].reshape(-1)))


def test_points_whose_divided_remainder_is_over_a_tenth_of_their_bound_are_written_multiplied():
    """``divided_ratio`` (stop 58): a point is written in the divided form only where its remainder
    is at most a tenth of its bound (it inflates the point's disc by up to ``1 + remainder /
    bound``); elsewhere the pair's lifted form, exact in the products. One contraction of a box
    four times the exact set's extent around the truth (a 3 % pair at five times the noise, many
    points with remainders between a tenth of the bound and the bound): both choices hold the
    linearised exact set (HiGHS, independent of the conic programs); the tenth's box lies inside the
    other's and is more than 10 % narrower somewhere."""
    import importlib.util
    from pathlib import Path

    from setmem_hil.identification.mode_group import GroupSettings, _Search

    spec = importlib.util.spec_from_file_location("_close_pair_box", Path(__file__).with_name("_close_pair_box.py"))
    helpers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    case = helpers.pair_box_around_truth(0.03, (4.0, 2.5), 5.0)
    w, g, E, ex_lo, ex_hi, lo, hi = case.w, case.g, case.E, case.ex_lo, case.ex_hi, case.lo, case.hi
    rho = linearised_group(w, g, lo, hi)[3]
    assert np.sum((rho > 0.1 * E) & (rho <= E)) >= 20  # the points the choice is about
    boxes = {}
    for ratio in (1.0, 0.1):
        out = _Search(w, g, E, GroupSettings(divided_ratio=ratio, workers=1)).contract(lo, hi)
        assert out is not None
        boxes[ratio] = out[:2]
        slack = 1e-6 * (ex_hi - ex_lo)
        assert np.all(out[0] <= ex_lo + slack) and np.all(out[1] >= ex_hi - slack), ratio
    (lo1, hi1), (lo01, hi01) = boxes[1.0], boxes[0.1]
    assert np.all(lo01 >= lo1 - 1e-12 * np.abs(lo1)) and np.all(hi01 <= hi1 + 1e-12 * np.abs(hi1))
    assert np.any(hi01 - lo01 < 0.9 * (hi1 - lo1))


def test_piece_hulls_cover_every_piece_with_at_most_the_count_asked_and_keep_a_slanted_set_thin():
    """:func:`mode_group.piece_hulls` (the polish's start, stop 58): every point of every piece lies
    in one of the hulls (sampled), there are at most ``count`` of them, and for pieces along a
    slanted line (a pair's residues going together) the hulls' total area is a small part of the
    one hull's."""
    from setmem_hil.identification.mode_group import piece_hulls

    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, 1.0, 200))
    centres = np.column_stack([t, 1.0 - t + 0.01 * rng.standard_normal(t.size)])
    pieces = [(c - 0.01, c + 0.01) for c in centres]
    hulls = piece_hulls(pieces, 8)
    assert len(hulls) == 8
    for lo, hi in pieces:
        for x in rng.uniform(lo, hi, size=(5, 2)):
            assert any(np.all(x >= h_lo) and np.all(x <= h_hi) for h_lo, h_hi in hulls)
    area = sum(np.prod(h_hi - h_lo) for h_lo, h_hi in hulls)
    whole = np.prod(np.max([h for _, h in pieces], axis=0) - np.min([l for l, _ in pieces], axis=0))
    assert area < 0.2 * whole
    assert piece_hulls(pieces[:3], 8) == pieces[:3]


@pytest.mark.slow
def test_the_polish_started_from_the_groups_leaves_holds_every_fitting_point_and_narrows_the_far_mode():
    """The final all-modes contraction started from the pair's last leaves (stop 58) against the
    same contraction from their hull (``polish_pieces=0``): both hold the truth and the extent
    reached by points checked to fit every line (a local search from the truth, independent of the
    conic programs); no interval of the pieces' answer is wider (beyond rounding), and the far
    mode's is narrower somewhere."""
    from setmem_hil.identification.algorithm import IdentifySettings
    from setmem_hil.identification.feasible_points import fitting_extent

    truth, data, prior = close_pair_case(0.01, residues=(4.0, 2.5), noise=5.0, n=120)
    box = prior.initial_bounds()
    inner_lo, inner_hi = fitting_extent(data.omega_rad_s, data.response, data.bound, box.lower.reshape(-1),
                                        box.upper.reshape(-1), truth.values.reshape(-1))
    results = {k: identify(data, prior, settings=IdentifySettings(polish_pieces=k)) for k in (0, 256)}
    for result in results.values():
        assert result.verified.all() and result.model.contains(truth).all()
        assert np.all(result.model.lower.reshape(-1) <= inner_lo) and np.all(result.model.upper.reshape(-1) >= inner_hi)
    hull, pieces = results[0].model, results[256].model
    assert np.all(pieces.width <= hull.width * (1 + 1e-9) + 1e-15), (pieces.width / hull.width)
    assert np.any(pieces.width[2] < 0.9 * hull.width[2]), (pieces.width / hull.width)


def test_polish_pieces_cover_every_combination_of_the_groups_leaves():
    """:func:`algorithm.polish_pieces`: with two groups of two modes and a fifth mode alone, at most
    ``most`` boxes, each inside the current box, the lone mode at its whole range, and every pair of
    leaves (one from each group) inside one of them."""
    from setmem_hil.identification.algorithm import polish_pieces

    rng = np.random.default_rng(2)
    lo, hi = np.zeros((5, 4)), np.ones((5, 4))

    def leaves(count):
        out = []
        for _ in range(count):
            a = rng.uniform(0.0, 0.9, size=(2, 4))
            out.append((a, a + 0.1))
        return tuple(out)

    groups = {(0, 1): leaves(30), (2, 3): leaves(12)}
    boxes = polish_pieces(groups, lo, hi, 16)
    assert 1 < len(boxes) <= 16
    for b_lo, b_hi in boxes:
        assert np.all(b_lo >= lo) and np.all(b_hi <= hi)
        assert np.all(b_lo[4] == lo[4]) and np.all(b_hi[4] == hi[4])
    for a_lo, a_hi in groups[(0, 1)]:
        for c_lo, c_hi in groups[(2, 3)]:
            assert any(np.all(b_lo[[0, 1]] <= a_lo) and np.all(b_hi[[0, 1]] >= a_hi)
                       and np.all(b_lo[[2, 3]] <= c_lo) and np.all(b_hi[[2, 3]] >= c_hi) for b_lo, b_hi in boxes)
    assert polish_pieces({(0, 1): ()}, lo, hi, 16) == ()


def test_a_centre_pole_on_a_measured_line_gives_no_nan_to_the_conic_program():
    """A box whose centre's pole sits a hair (1e-155) from a measured line: the remainder and the
    pole's derivative overflow; the disc form drops the pole term, and 0 x inf was a NaN in the
    cone's row (an uncertified bound in the 0.5 % benchmark, after an overflow warning)."""
    import warnings

    from setmem_hil.identification.mode_group import linearised_group

    omega = np.array([9.0, 10.0, 11.0])
    lo = np.array([1e-156, 100.0, 0.0, 1.0])
    hi = np.array([3e-156, 100.0, 0.0, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning either
        r_c, J, err, rho = linearised_group(omega, np.zeros(3, dtype=complex), lo, hi)
    assert np.all(np.isfinite(J)) and not np.any(np.isnan(rho)) and np.all(np.isfinite(r_c))
    assert np.isfinite(rho[[0, 2]]).all() and rho[1] > 1e100  # the other lines still bound



def _pair_with_a_flaky_solver(monkeypatch, parameter: int, when, max_boxes: int = 24):
    """The 1 % pair's group search (100 lines) with the conic solver failing, in the boxes
    ``when(lo, hi, truth)`` picks, to certify the upper bound of ``parameter``: the box's own bound
    kept and flagged, as a nearly empty box's ``AlmostPrimalInfeasible`` does on some machines and
    not on others (the slow tier's far-mode test at d820639). Returns the truth, the root box's
    upper bounds, the result and the number of injected failures."""
    from dataclasses import replace

    from setmem_hil.identification.certified_cone_program import AffineConeProgram
    from setmem_hil.identification.mode_group import GroupSettings, identify_group
    from setmem_hil.model.modal_model import ModalParameters

    truth, data, prior = close_pair_case(0.01, n=100)
    x_true = truth.values[:2].reshape(-1)
    real, injected = AffineConeProgram.bound_box, [0]

    def flaky(self, C, box_lo, box_hi):
        sol = real(self, C, box_lo, box_hi)
        if not sol.feasible or not self.free[parameter] or not when(box_lo, box_hi, x_true):
            return sol
        injected[0] += 1
        upper = sol.upper.copy()
        upper[parameter] = box_hi[parameter]
        return replace(sol, upper=upper, unverified=sol.unverified + (f"upper bound of parameter {parameter}: injected",),
                       kept=sol.kept + ((parameter, -1),))

    monkeypatch.setattr(AffineConeProgram, "bound_box", flaky)
    far = ModalParameters(truth.values[2:])
    g = data.response - far.frequency_response(data.omega_rad_s)
    box = prior.initial_bounds()
    result = identify_group(data.omega_rad_s, g, data.bound, box.lower[:2], box.upper[:2], GroupSettings(max_boxes=max_boxes))
    return x_true, box.upper[:2].reshape(-1), result, injected[0]


A0_OF_MODE_1 = 1  # index of mode 1's a0 in the group's (a1, a0, b1, b0) x 2
A0_OF_MODE_2 = 5  # mode 2's


def test_an_uncertified_bound_inside_the_answer_leaves_the_answer_verified(monkeypatch):
    """A box whose upper bound of mode 2's a0 stays uncertified but lies below the true a0 cannot
    hold the answer's bound (the answer holds the truth): the answer stays verified and holds the
    truth. (Every flag once made the whole group unverified.) Mode 2's: with the multiplied
    points' radii affine (stop 59) no box of the first 24 lies below mode 1's true a0."""
    p = A0_OF_MODE_2
    truth, _, result, injected = _pair_with_a_flaky_solver(monkeypatch, p, lambda lo, hi, x: hi[p] < x[p])
    assert injected > 0
    assert result.verified, result.unverified_reason
    lo, hi = result.lower.reshape(-1), result.upper.reshape(-1)
    assert np.all(lo <= truth) and np.all(truth <= hi)


def test_an_uncertified_bound_the_answer_rests_on_is_reported(monkeypatch):
    """The same failure in every box of a search cut short after its first box (its halves become
    leaves as they stand): the answer's upper bound of mode 1's a0 is the searched box's own, and the
    result says so (unverified, naming the bound) while still holding the truth. (With the search
    run further, the boxes above the truth are proved empty and the answer's bound is a cut: exact.)"""
    p = A0_OF_MODE_1
    truth, root_hi, result, injected = _pair_with_a_flaky_solver(monkeypatch, p, lambda lo, hi, x: True, max_boxes=1)
    assert injected > 0 and result.exhausted
    assert not result.verified and "upper bound of parameter 1: injected" in result.unverified_reason
    assert result.upper.reshape(-1)[p] == root_hi[p]
    lo, hi = result.lower.reshape(-1), result.upper.reshape(-1)
    assert np.all(lo <= truth) and np.all(truth <= hi)


def test_a_flag_from_an_early_group_round_is_cleared_by_a_later_certified_search(monkeypatch):
    """A group search left unverified in the first round, certified in every later one: the
    answer is verified (each search starts from a box that holds the data's set, so the last
    certified search's bounds are certified); the same failure injected into the last search
    (the all-modes polish) is reported."""
    from dataclasses import replace

    from setmem_hil.identification import algorithm

    truth, data, prior = close_pair_case(0.03, n=120)
    real = algorithm.identify_group

    def run_with_failure_at(which):
        calls = []

        def flaky(*args, **kwargs):
            found = real(*args, **kwargs)
            calls.append(found)
            return replace(found, verified=False, unverified_reason="injected") if which(len(calls)) else found

        monkeypatch.setattr(algorithm, "identify_group", flaky)
        return identify(data, prior), len(calls)

    result, n_calls = run_with_failure_at(lambda k: k == 1)
    assert n_calls >= 3 and result.groups  # a round per group, then the polish
    assert result.verified.all(), result.unverified_reason
    assert result.model.contains(truth).all()
    last, n_calls = run_with_failure_at(lambda k: k == n_calls)
    assert not last.verified.all() and any("injected" in r for r in last.unverified_reason)


def test_the_polish_cuts_the_parameter_of_a_grouped_mode_widest_against_the_witnesses():
    """The polish's split rule (stop 59, :func:`mode_group._relatively_widest`): among the free
    parameters of the modes named, the one whose box is widest in units of the witnesses' hull,
    checked against a plain loop over every parameter; a mode not named is never cut, nor a fixed
    parameter; none free gives -1."""
    from setmem_hil.identification.mode_group import _relatively_widest

    rng = np.random.default_rng(2)
    for _ in range(200):
        inner_lo = rng.normal(size=12)
        inner = (inner_lo, inner_lo + rng.uniform(0.1, 2.0, 12))
        lo = inner[0] - rng.uniform(0.0, 1.0, 12)
        hi = inner[1] + rng.uniform(0.0, 1.0, 12)
        fixed = rng.uniform(size=12) < 0.15
        hi[fixed] = lo[fixed]
        modes = tuple(sorted(rng.choice(3, size=rng.integers(1, 3), replace=False).tolist()))
        best, best_ratio = -1, -np.inf
        for p in range(12):
            if p // 4 in modes and hi[p] > lo[p]:
                ratio = (hi[p] - lo[p]) / (inner[1][p] - inner[0][p])
                if ratio > best_ratio:
                    best, best_ratio = p, ratio
        assert _relatively_widest(inner, lo, hi, modes) == best


def test_the_polish_budget_is_the_settings_or_the_rule(monkeypatch):
    """``IdentifySettings.polish_boxes`` (stop 62) sets the final contraction's boxes (beyond its
    pieces) and ``polish_second_order`` (stop 63) its form; without them, the rule's 240 boxes and
    the second-order form where a mode is outside every group (the far mode here).
    Either answer holds the truth."""
    from setmem_hil.identification import algorithm

    truth, data, prior = close_pair_case(0.03, n=120)
    real = algorithm.identify_group

    def budgets_of(settings):
        seen = []

        def spy(omega, g, E, lo, hi, group_settings, pieces=()):
            if group_settings.lift_pairs:  # only the polish lifts pairs
                seen.append((group_settings.max_boxes - len(pieces), group_settings.second_order))
            return real(omega, g, E, lo, hi, group_settings, pieces)

        monkeypatch.setattr(algorithm, "identify_group", spy)
        result = identify(data, prior, settings=settings)
        assert result.model.contains(truth).all() and result.groups == ((0, 1),)
        return seen

    assert set(budgets_of(algorithm.IdentifySettings(polish_boxes=5, polish_second_order=False))) == {(5, False)}
    # the rule where a mode is outside every group: 240 boxes, the divided points to second order (stop 63)
    assert set(budgets_of(algorithm.IdentifySettings())) == {(algorithm.POLISH_BOXES_LONE_MODE, True)}
