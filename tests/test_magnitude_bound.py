"""The affine bound of a multiplied denominator's magnitude (issue 47, stop 59).

Independent truths: the magnitude evaluated directly at sampled points of the box (products
exact), the pointwise constraint evaluated with the model itself, and the linearised exact feasible
set in HiGHS (:func:`exact_set.linearised_extent`), independent of the conic programs.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.identification.embedding import denominator_max
from setmem_hil.identification.mode_group import GroupSettings, _Search, denominator_bound
from setmem_hil.model.modal_model import A0, A1, ModalParameters, modal_response
from setmem_hil.sim_backends.close_pair import close_pair_case

_spec = importlib.util.spec_from_file_location("_close_pair_box", Path(__file__).with_name("_close_pair_box.py"))
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)
_pair_box_around_truth = _helpers.pair_box_around_truth


def _denominator(x_mode, w):
    return (x_mode[A0] - w * w) + 1j * w * x_mode[A1]


@pytest.mark.parametrize("modes", [1, 2])
def test_the_affine_bound_is_above_the_magnitude_everywhere_in_the_box_and_below_the_box_maximum_at_its_centre(modes):
    """Boxes around two poles 1 % apart near 10 rad/s, lines through the resonances: at 200 sampled
    points of each box (the products taken exactly), ``U`` is at least ``|D|`` (one mode) or
    ``|D_1 D_2|`` (a pair) wherever the bound is used; where used, its value at the centre is
    below the box's maximum (eq. 3.34), which it replaces."""
    rng = np.random.default_rng(3)
    w = np.linspace(9.5, 10.8, 80)
    centre = np.array([[0.1, 100.0, 0.0, 4.0], [0.1005, 102.01, 0.0, 2.5]])[:modes]
    used = 0
    for _ in range(30):
        half = np.abs(centre) * rng.uniform(1e-4, 3e-3, centre.shape) + rng.uniform(1e-3, 3e-2, centre.shape)
        lo, hi = (centre - half).reshape(-1), (centre + half).reshape(-1)
        pairs = np.array([(p, 4 + q) for p in (A1, A0) for q in (A1, A0)]) if modes == 2 else ()
        box_max = np.prod([denominator_max(w, lo[4 * i + A0], hi[4 * i + A0], hi[4 * i + A1]) for i in range(modes)], axis=0)
        bound = denominator_bound(w, lo, hi, pairs, box_max)
        assert np.all(bound.constant[bound.usable] < box_max[bound.usable])
        used += int(bound.usable.sum())
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for y in rng.uniform(-1.0, 1.0, size=(200, lo.size)):
            x = (c + h * y).reshape(modes, 4)
            magnitude = np.prod([np.abs(_denominator(x[i], w)) for i in range(modes)], axis=0)
            z = np.array([y[p] * y[q] for p, q in pairs]) if modes == 2 else np.zeros(0)
            U = bound.constant + bound.slope @ y + bound.product_slope @ z
            assert np.all(U[bound.usable] >= magnitude[bound.usable] * (1.0 - 1e-12))
    assert used > 200  # the bound is used at many points, not only where it cannot matter


@pytest.mark.parametrize("modes", [2, 3])
def test_every_point_of_a_box_that_fits_a_line_satisfies_that_lines_cone(modes):
    """The cones a box's program uses (divided, lifted or mixed, radii affine where tighter) hold
    every parameter of the box that fits the line: at sampled points, wherever ``|g - G(x)| <= E``
    (the model evaluated directly) the cone's inequality holds with the products exact. A 1 %
    same-sign pair at five times the noise; ``modes = 2`` with the far mode subtracted exactly."""
    rng = np.random.default_rng(11)
    truth, data, _ = close_pair_case(0.01, residues=(4.0, 2.5), noise=5.0)
    w, g, E = data.omega_rad_s, data.response, data.bound
    if modes == 2:
        g = g - ModalParameters(truth.values[2:]).frequency_response(w)
    x0 = truth.values[:modes].reshape(-1)
    checked = 0
    for _ in range(25):
        width = np.abs(x0) * rng.uniform(1e-3, 3e-2) + rng.uniform(1e-3, 2e-2)
        lo, hi = x0 - width * rng.uniform(0.2, 1.0, x0.size), x0 + width * rng.uniform(0.2, 1.0, x0.size)
        r_c, J, err, C, products, active, slopes = _Search(w, g, E, GroupSettings(workers=1))._cones(lo, hi, np.arange(w.size))
        assert slopes is not None
        c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for y in rng.uniform(-1.0, 1.0, size=(20, x0.size)):
            x = c + h * y
            lhs, radius = r_c + J @ (x - c), C + slopes[0] @ (x - c)
            if products is not None:
                z = y[products.pairs[:, 0]] * y[products.pairs[:, 1]]
                lhs, radius = lhs + products.K @ z, radius + slopes[1] @ z
            fits = np.abs(g[active] - modal_response(x.reshape(-1, 4), w[active]).sum(axis=0)) <= E[active]
            assert np.all(np.abs(lhs[fits]) <= radius[fits] * (1.0 + 1e-9))
            checked += int(fits.sum())
    assert checked > 1000


def test_one_contraction_with_the_affine_radius_holds_the_exact_set_and_is_narrower():
    """One contraction of a box four times the exact set's extent around the truth (a 3 % same-sign
    pair at five times the noise): with the multiplied points' radii affine (stop 59) and with the
    box's maximum (eq. 3.34), both boxes hold the linearised exact set (HiGHS, independent of the
    conic programs), and the affine one is narrower by more than a fifth in every parameter."""
    case = _pair_box_around_truth(0.03, (4.0, 2.5), 5.0)
    w, g, E, ex_lo, ex_hi, lo, hi = case.w, case.g, case.E, case.ex_lo, case.ex_hi, case.lo, case.hi
    widths = {}
    for affine in (False, True):
        out = _Search(w, g, E, GroupSettings(affine_radius=affine, workers=1)).contract(lo, hi)
        assert out is not None
        slack = 1e-6 * (ex_hi - ex_lo)
        assert np.all(out[0] <= ex_lo + slack) and np.all(out[1] >= ex_hi - slack), affine
        widths[affine] = out[1] - out[0]
    assert np.all(widths[True] < 0.8 * widths[False])


@pytest.mark.parametrize("modes", [2, 3])
def test_a_line_without_a_bound_is_left_out_silently(modes):
    """A line whose bound is infinite (it constrains nothing: a campaign's unusable line) is left out
    of the program without a floating-point warning reaching the user (inf times a zero slope), and
    the other lines' cones are those of the data without it."""
    import warnings

    truth, data, _ = close_pair_case(0.01, residues=(4.0, 2.5), noise=5.0, n=120)
    w, g, E = data.omega_rad_s, data.response, data.bound.copy()
    x0 = truth.values[:modes].reshape(-1)
    lo, hi = x0 - 0.02 * np.abs(x0) - 0.01, x0 + 0.02 * np.abs(x0) + 0.01
    resonant = int(np.argmin(np.abs(w - 10.0)))
    E[resonant] = np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = _Search(w, g, E, GroupSettings(workers=1))._cones(lo, hi, np.arange(w.size))
    keep = np.arange(w.size) != resonant
    ref = _Search(w[keep], g[keep], E[keep], GroupSettings(workers=1))._cones(lo, hi, np.arange(keep.sum()))
    assert not out[5][resonant]
    assert np.array_equal(out[3], ref[3]) and np.array_equal(out[6][0], ref[6][0])
