"""mu-bar certified on whole frequency intervals (issue 27, item 3).

Independent truths: the eigenvalues of ``Phi(w)`` on a dense grid (where they change sign), the
bound of eq. (2.15) evaluated with :func:`bound_at_scalings` (another formula than the Lemma 2.1
form the certificate uses), and dense precise mu-bar solves around a peak built on purpose
between two grid points.
"""

import math

import numpy as np
import pytest

from setmem_hil.design.safeguard import safeguarded_design
from setmem_hil.campaign.runner import goal_certified
from setmem_hil.io.procedure import Goal
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import THESIS_WEIGHTS
from setmem_hil.robust.analysis import analyze_robust_performance, default_omega_grid
from setmem_hil.robust.augmented_plant import augmented_plant
from setmem_hil.robust.h2_design import h2_controller_for_plant
from setmem_hil.robust.mixed_mu import MuStructure, bound_at_scalings, mixed_mu_upper
from setmem_hil.robust.mu_certificate import certify_band, crossing_frequencies
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.sim_backends.beam import beam_parameters

TABLE_B1_LOWER = [[2.0911e-9, 8.8827e-1, 0.0, 2.7028], [4.5511e-9, 3.3851e1, 0.0, -1.4572], [1.6299e-9, 2.6725e2, 0.0, -7.8492]]
TABLE_B1_UPPER = [[1.2140e-1, 1.2333, 0.0, 7.6251], [5.3030e-1, 4.3162e1, 0.0, 7.6061], [2.5572, 3.5747e2, 0.0, 1.5549e1]]


def closed_loop_of(model: IntervalModel, controller=None):
    plant = augmented_plant(uncertain_plant(model), THESIS_WEIGHTS)
    K = h2_controller_for_plant(plant) if controller is None else controller
    return plant.closed_loop(K), MuStructure(plant.n_real, plant.n_complex)


@pytest.fixture(scope="module")
def table_b1_loop():
    system, structure = closed_loop_of(IntervalModel(TABLE_B1_LOWER, TABLE_B1_UPPER))
    w = default_omega_grid()
    return system, structure, w, mixed_mu_upper(system.frequency_response(w), structure, tol=1e-4, max_iter=60)


def phi_eigenvalues(system, d, g, beta, w):
    """All eigenvalues of ``Phi(w) = M^* D_L M + j(G_L M - M^* G_L) - beta^2 D_L`` (eq. 2.16)."""
    d_l, g_l = d**2, d**2 * g
    M = system.frequency_response(w)
    Mh = np.conj(np.swapaxes(M, 1, 2))
    GM = g_l[:, None] * M
    Phi = Mh @ (d_l[:, None] * M) + 1j * (GM - np.conj(np.swapaxes(GM, 1, 2))) - beta**2 * np.diag(d_l)
    return np.linalg.eigvalsh(Phi)


def test_every_sign_change_of_phi_is_a_computed_crossing(table_b1_loop):
    system, _, w, bound = table_b1_loop
    dense = np.geomspace(0.1, 1000.0, 12001)
    for k in (20, 90, 120, 160):  # scalings of four grid points, at a level 10 % above their bound
        d, g, beta = bound.d[k], bound.g[k], 1.1 * bound.beta[k]
        eig = phi_eigenvalues(system, d, g, beta, dense)
        changes = np.flatnonzero(np.any(np.diff(np.sign(eig), axis=0) != 0, axis=1))
        assert changes.size > 0
        cuts = crossing_frequencies(system, d**2, d**2 * g, beta)
        for i in changes:
            lo, hi = dense[i], dense[i + 1]
            assert np.any((cuts >= lo * (1 - 1e-9)) & (cuts <= hi * (1 + 1e-9))), f"sign change in [{lo}, {hi}] missed"


def test_every_certified_piece_holds_on_a_dense_grid_and_the_pieces_cover_the_band(table_b1_loop):
    system, structure, w, bound = table_b1_loop
    cert = certify_band(system, structure, (0.1, 1000.0), w, bound)
    assert cert.certified and cert.n_intervals == len(cert.pieces) >= 1
    assert cert.level == pytest.approx(cert.peak * (1 + 1e-4))
    for lo, hi, d, g in cert.pieces:
        inside = np.geomspace(lo, hi, 60)
        beta = bound_at_scalings(system.frequency_response(inside), np.broadcast_to(d, (60, d.size)), np.broadcast_to(g, (60, g.size)))
        assert np.all(beta <= cert.level * (1 + 1e-9)), (lo, hi, beta.max(), cert.level)
    ends = sorted((lo, hi) for lo, hi, _, _ in cert.pieces)
    assert ends[0][0] == 0.1 and ends[-1][1] == 1000.0
    for (_, hi), (lo, _) in zip(ends[:-1], ends[1:]):
        assert lo <= hi, f"gap between {hi} and {lo} rad/s"
    # and the level bounds mu-bar at frequencies nobody chose: 800 precise solves
    dense = np.geomspace(0.1, 1000.0, 800)
    assert mixed_mu_upper(system.frequency_response(dense), structure).beta.max() <= cert.level


def lightly_damped_model(omega_rad_s=2.9, zeta=1e-4, b0=0.05) -> IntervalModel:
    """The thesis beam (3 modes) plus a weak, very lightly damped mode inside the control band, at
    a frequency between two of the 200 grid points (half-power width 2 zeta w = 6e-4 rad/s against
    a grid step of 4.7 %)."""
    values = np.vstack([beam_parameters().truncated(3).values, [2 * zeta * omega_rad_s, omega_rad_s**2, 0.0, b0]])
    return IntervalModel(values.copy(), values.copy())


@pytest.fixture(scope="module")
def missed_peak():
    model = lightly_damped_model()
    return model, analyze_robust_performance(model)


def test_a_peak_between_grid_points_is_found_and_certified(missed_peak):
    model, analysis = missed_peak
    system, structure = closed_loop_of(model, analysis.controller)
    grid = default_omega_grid()
    on_grid = mixed_mu_upper(system.frequency_response(grid), structure).beta.max()
    assert on_grid < 1.0  # what the grid alone would claim: goal reached
    assert analysis.mu_peak_grid < 1.0 < analysis.mu_peak and analysis.mu_peak_certified
    # the truth, independently: a dense precise sweep across the closed loop's resonance
    window = np.linspace(analysis.mu_peak_omega * 0.995, analysis.mu_peak_omega * 1.005, 4001)
    dense = mixed_mu_upper(system.frequency_response(window), structure).beta
    print(f"\ngrid peak {on_grid:.4f}; certified {analysis.mu_peak:.4f} at {analysis.mu_peak_omega:.5f} rad/s; "
          f"dense {dense.max():.4f}; {analysis.mu_certified_intervals} intervals")
    assert dense.max() > 1.0
    assert dense.max() <= analysis.mu_certified_level * (1 + 1e-9)
    assert analysis.mu_peak == pytest.approx(dense.max(), rel=1e-3)


def test_the_campaign_stops_on_the_certified_value_not_the_grid(missed_peak):
    model, analysis = missed_peak
    goal = Goal(mu_target=1.0, max_experiments=5)
    outcome = safeguarded_design(model, None, lambda m, k: analysis)
    assert analysis.mu_peak_grid < goal.mu_target  # the grid's value would have stopped it
    assert not goal_certified(outcome, goal)

    class UncertifiedAnalysis:  # a bound below the goal at every grid point, but not proved between them
        mu_peak, mu_peak_certified, controller, certified_mu = 0.5, False, None, math.inf

    assert not goal_certified(safeguarded_design(model, None, lambda m, k: UncertifiedAnalysis()), goal)
    demo = analyze_robust_performance(IntervalModel.point(beam_parameters().truncated(3)))
    assert demo.mu_peak_certified and goal_certified(safeguarded_design(model, None, lambda m, k: demo), goal)


def test_a_budget_too_small_is_reported_as_not_certified(table_b1_loop):
    system, structure, w, bound = table_b1_loop
    cert = certify_band(system, structure, (0.1, 1000.0), w, bound, max_scalings=1)
    assert not cert.certified and cert.n_scalings == 1
    assert cert.level >= float(bound.beta.max())  # the level is still the evaluated peak's, never lower
