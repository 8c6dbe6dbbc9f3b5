"""H2 compensator of section 6.3.1: sign convention and an independent check of the H2 norm."""

import numpy as np
import pytest

from setmem_hil.robust.augmented_plant import StateSpaceMatrices, augmented_plant
from setmem_hil.errors import SolverError
from setmem_hil.robust.h2_design import design_h2_controller, h2_controller_for_plant, h2_norm
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

LOWER = [[0.01, 0.9, 0.0, 3.5], [0.1, 37.0, 0.0, 3.0], [0.2, 290.0, 0.0, 2.0]]
UPPER = [[0.03, 1.1, 0.0, 4.5], [0.3, 41.0, 0.0, 5.0], [0.5, 320.0, 0.0, 6.0]]


@pytest.fixture(scope="module")
def design():
    model = IntervalModel(LOWER, UPPER)
    plant = augmented_plant(uncertain_plant(model), THESIS_WEIGHTS)
    K = h2_controller_for_plant(plant)
    return plant, K, plant.closed_loop(K)


def test_closed_loop_stable_and_controller_order(design):
    plant, K, cl = design
    assert K.nstates == plant.A.shape[0] == 15
    assert np.max(np.linalg.eigvals(cl.A).real) < 0


@pytest.mark.slow
def test_h2_norm_gramian_matches_modal_integral(design):
    _, _, cl = design
    gram = h2_norm(cl)
    # ||T||_2^2 = int_0^inf ||C e^{At} B||_F^2 dt in closed form over the modes of A:
    # sum_ij (Cm^* Cm)_ij (Bm Bm^*)_ji * (-1 / (conj(l_i) + l_j)),  A = V diag(l) V^{-1}
    lam, V = np.linalg.eig(cl.A)
    Bm = np.linalg.solve(V, cl.B)
    Cm = cl.C @ V
    kernel = -1.0 / (np.conj(lam)[:, None] + lam[None, :])
    modal = np.sqrt(np.real(np.sum((Cm.conj().T @ Cm) * (Bm @ Bm.conj().T).T * kernel)))
    assert gram == pytest.approx(modal, rel=1e-6)
    # and a coarse check against the frequency-domain definition (1/pi) int ||T(jw)||_F^2 dw
    w = np.logspace(-3, 8, 40001)  # W2 rolls off only beyond its extra pole at 1e4 rad/s
    F = cl.frequency_response(w)
    quad = np.sqrt(np.trapezoid(np.sum(np.abs(F) ** 2, axis=(1, 2)), w) / np.pi)
    assert gram == pytest.approx(quad, rel=2e-3)


def test_controller_is_locally_h2_optimal(design):
    plant, K, cl = design
    base = h2_norm(cl)
    rng = np.random.default_rng(12)
    Ak, Bk, Ck = (np.asarray(x, dtype=float) for x in (K.A, K.B, K.C))
    for _ in range(10):
        scale = 1e-3
        pert = StateSpaceMatrices(
            Ak + scale * np.abs(Ak).max() * rng.normal(size=Ak.shape) * (Ak != 0),
            Bk + scale * np.abs(Bk).max() * rng.normal(size=Bk.shape),
            Ck + scale * np.abs(Ck).max() * rng.normal(size=Ck.shape),
            np.zeros((1, 1)),
        )
        other = h2_norm(plant.closed_loop(pert))
        assert other >= base * (1 - 1e-9)


def test_positive_feedback_convention(design):
    # with u = K y the sensitivity is S = 1 / (1 - G K); the channel w_2 -> z_2 is W_2 S
    plant, K, cl = design
    p = plant.n_real
    w = np.array([0.5, 2.0, 4.4, 9.0])
    T = cl.frequency_response(w)[:, p + 1, p + 1]
    s = 1j * w
    model = IntervalModel(LOWER, UPPER)
    G = model.midpoint.frequency_response(w)
    Kjw = np.array([np.asarray(K(x)).reshape(()) for x in s])
    n2, d2 = THESIS_WEIGHTS.w2_for_design()
    W2 = np.polyval(n2, s) / np.polyval(d2, s)
    assert np.allclose(T, W2 / (1 - G * Kjw), rtol=1e-8)


def test_nominal_beam_design():
    K = design_h2_controller(IntervalModel.point(beam_parameters().truncated(3)))
    assert K.nstates == 15


def test_w2_without_extra_pole_is_refused():
    model = IntervalModel(LOWER, UPPER)
    w = Weights(w2_extra_pole_rad_s=None)
    with pytest.raises(SolverError, match="D11"):
        design_h2_controller(model, w)


def test_our_lower_lft_agrees_with_python_controls(design):
    """``AugmentedPlant.closed_loop`` (the mu loop's hot path, kept on plain matrices) against
    python-control's ``StateSpace.lft`` of the same plant and compensator: the same system (issue 40,
    item 6: our own LFT stays only where it is the same as the library's)."""
    plant, K, cl = design
    theirs = plant.to_statespace().lft(K, ny=1, nu=1)
    w = np.geomspace(0.05, 500.0, 60)
    ours_response = cl.frequency_response(w)
    # both evaluated the same way (a linear solve at each j w): the comparison is of the LFTs
    theirs_response = StateSpaceMatrices(theirs.A, theirs.B, theirs.C, theirs.D).frequency_response(w)
    assert np.max(np.abs(ours_response - theirs_response)) <= 1e-10 * np.max(np.abs(theirs_response))


def test_h2_norm_is_python_controls():
    """``h2_norm`` is python-control's ``norm(sys, 2)``; it agrees with the Gramian formula."""
    import control
    from scipy.linalg import solve_continuous_lyapunov

    rng = np.random.default_rng(3)
    A = -np.diag(rng.uniform(0.5, 3.0, 6)) + 0.2 * rng.standard_normal((6, 6))
    system = StateSpaceMatrices(A, rng.standard_normal((6, 2)), rng.standard_normal((3, 6)), np.zeros((3, 2)))
    P = solve_continuous_lyapunov(A, -system.B @ system.B.T)
    gram = np.sqrt(np.trace(system.C @ P @ system.C.T))
    assert h2_norm(system) == pytest.approx(gram, rel=1e-10)
    assert h2_norm(system) == pytest.approx(control.norm(control.ss(A, system.B, system.C, system.D), 2), rel=1e-12)
