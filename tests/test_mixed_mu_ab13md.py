"""The upper bound against SLICOT AB13MD (Fan-Tits-Doyle), the public peer."""

import numpy as np
import pytest

slycot = pytest.importorskip("slycot")

from setmem_hil.robust.augmented_plant import augmented_plant  # noqa: E402
from setmem_hil.robust.h2_design import h2_controller_for_plant  # noqa: E402
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper  # noqa: E402
from setmem_hil.model.modal_model import IntervalModel  # noqa: E402
from setmem_hil.robust.analysis import analyze_robust_performance, default_omega_grid  # noqa: E402
from setmem_hil.robust.uncertain_plant import uncertain_plant  # noqa: E402
from setmem_hil.model.weights import THESIS_WEIGHTS  # noqa: E402

# Table B-1 (appendix B); the a11 upper bound is the table's stray last entry (see test_robust_analysis)
TABLE_B1_LOWER = [[2.0911e-9, 8.8827e-1, 0.0, 2.7028], [4.5511e-9, 3.3851e1, 0.0, -1.4572], [1.6299e-9, 2.6725e2, 0.0, -7.8492]]
TABLE_B1_UPPER = [[1.2140e-1, 1.2333, 0.0, 7.6251], [5.3030e-1, 4.3162e1, 0.0, 7.6061], [2.5572, 3.5747e2, 0.0, 1.5549e1]]


def ab13md(M, p):
    n = M.shape[0]
    return slycot.ab13md(M, np.ones(n, dtype=int), np.array([1] * p + [2] * (n - p)))[0]


@pytest.mark.parametrize("p,n", [(2, 4), (4, 6), (5, 7), (9, 11)])
def test_random_mixed_structures_never_above_ab13md(p, n):
    rng = np.random.default_rng(100 + n)
    M = rng.normal(size=(6, n, n)) + 1j * rng.normal(size=(6, n, n))
    ours = mixed_mu_upper(M, MuStructure(p, n - p), tol=1e-7, max_iter=300).beta
    ref = np.array([ab13md(Mk, p) for Mk in M])
    assert np.all(ours <= ref * (1 + 1e-4)), np.max(ours / ref - 1)


@pytest.fixture(scope="module")
def beam_closed_loop():
    model = IntervalModel(TABLE_B1_LOWER, TABLE_B1_UPPER)
    plant = augmented_plant(uncertain_plant(model), THESIS_WEIGHTS)
    return model, plant.closed_loop(h2_controller_for_plant(plant))


@pytest.mark.slow
def test_beam_closed_loop_grid_never_above_ab13md(beam_closed_loop):
    _, cl = beam_closed_loop
    w = default_omega_grid()
    M = cl.frequency_response(w)
    ours = mixed_mu_upper(M, MuStructure(9, 2), tol=1e-6, max_iter=60).beta
    ref = np.array([ab13md(Mk, 9) for Mk in M])
    rel = ours / ref - 1
    print(f"\nbeam grid: largest (ours / ab13md - 1) = {rel.max():.2e}, smallest = {rel.min():.2e}")
    assert np.all(rel <= 1e-4)


@pytest.mark.slow
def test_analysis_peak_never_above_ab13md(beam_closed_loop):
    model, cl = beam_closed_loop
    r = analyze_robust_performance(model)
    ref = ab13md(cl.frequency_response([r.mu_peak_omega])[0], 9)
    assert r.mu_peak <= ref * (1 + 1e-4)
    # every reported value, grid and refinement points alike
    M = cl.frequency_response(r.omega)
    ab = np.array([ab13md(Mk, 9) for Mk in M])
    assert np.all(r.mu <= ab * (1 + 1e-4)), np.max(r.mu / ab - 1)
