"""mu-sensitivities (Theorems 4.2-4.3, steps 1-5 of 4.2.2) against central finite differences."""

import numpy as np
import pytest

from setmem_hil.robust.augmented_plant import augmented_plant
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.robust.mu_sensitivity import beta_derivatives, top_eigenspace
from setmem_hil.robust.analysis import analyze_robust_performance
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.model.weights import THESIS_WEIGHTS

TIGHT = dict(tol=1e-9, max_iter=200)
TABLE_B1_LOWER = [[2.0911e-9, 8.8827e-1, 0.0, 2.7028], [4.5511e-9, 3.3851e1, 0.0, -1.4572], [1.6299e-9, 2.6725e2, 0.0, -7.8492]]
TABLE_B1_UPPER = [[1.2140e-1, 1.2333, 0.0, 7.6251], [5.3030e-1, 4.3162e1, 0.0, 7.6061], [2.5572, 3.5747e2, 0.0, 1.5549e1]]


def shrunk(M, i, eps):
    """``A M A`` with ``A = diag(1, .., 1 - eps, .., 1)`` (Lemma 2.2)."""
    a = np.ones(M.shape[0])
    a[i] = 1.0 - eps
    return a[:, None] * M * a[None, :]


def central_difference(M, s, i, h=1e-3):
    # the recomputed bounds are accurate to ~1e-7..1e-6 relative, so the difference quotient
    # carries ~1e-6 beta / h absolute noise; it matters only for derivatives near zero (a real
    # block whose optimal scaling runs off along d_k -> 0), hence h = 1e-2 on random cases
    up = mixed_mu_upper(shrunk(M, i, h), s, **TIGHT).beta[0]
    down = mixed_mu_upper(shrunk(M, i, -h), s, **TIGHT).beta[0]
    return (up - down) / (2 * h)


def simple_top(bound, gap=1e-2):
    lam = bound.eigenvalues[0]
    return lam[1] < (1 - gap) * lam[0]


def bounded_scalings(bound, gamma=1e-3):
    """Assumption 4.1: the optimal scalings stay inside (gamma, 1/gamma) (here relative to their
    geometric mean, and g relative to beta); at a ray optimum (d_k -> 0) Lemma 4.1 does not apply."""
    d = bound.d[0] / np.exp(np.mean(np.log(bound.d[0])))
    g = np.abs(bound.g[0]) / bound.beta[0]
    return bool(np.all(d > gamma) and np.all(d < 1 / gamma) and np.all(g < 1 / gamma))


def test_beam_table_b1_peak_matches_finite_differences():
    model = IntervalModel(TABLE_B1_LOWER, TABLE_B1_UPPER)
    r = analyze_robust_performance(model)
    plant = augmented_plant(uncertain_plant(model), THESIS_WEIGHTS)
    M = plant.closed_loop(r.controller).frequency_response([r.mu_peak_omega])[0]
    s = MuStructure(9, 2)
    b = mixed_mu_upper(M, s, **TIGHT)
    assert simple_top(b) and bounded_scalings(b)
    analytic = beta_derivatives(M, b, 0)
    print()
    for i, name in enumerate(plant.names):
        fd = central_difference(M, s, i)
        print(f"  {name}: analytic {-analytic[i]:.6g}  finite difference {-fd:.6g}")
        assert analytic[i] == pytest.approx(fd, rel=2e-2, abs=1e-6)
        # the analysis reports s_i = -d mu / d eps at that peak
        assert r.sensitivities[name] == pytest.approx(-fd, rel=2e-2, abs=1e-6)


def test_random_mixed_cases_with_simple_top_eigenvalue():
    # where Assumption 4.1 holds (bounded optimal scalings) and the top eigenvalue is simple
    rng = np.random.default_rng(2024)
    s = MuStructure(3, 2)
    checked = 0
    for _ in range(30):
        M = rng.normal(size=(5, 5)) + 1j * rng.normal(size=(5, 5))
        b = mixed_mu_upper(M, s, **TIGHT)
        if not (simple_top(b, 5e-2) and bounded_scalings(b)):
            continue
        analytic = beta_derivatives(M, b, 0)
        for i in range(5):
            assert analytic[i] == pytest.approx(central_difference(M, s, i, h=1e-2), rel=2e-2, abs=1e-3)
        assert np.all(analytic <= 1e-9)  # Lemma 2.2: shrinking never raises the bound
        checked += 1
        if checked == 3:
            break
    assert checked == 3


def test_top_eigenspace_takes_the_repeated_cluster():
    lam = np.array([2.0, 2.0 - 1e-9, 1.0])
    U = np.eye(3)
    assert top_eigenspace(lam, U).shape == (3, 2)
    assert top_eigenspace(np.array([2.0, 1.0, 0.5]), U).shape == (3, 1)


def test_repeated_top_eigenvalue_uses_the_fastest_direction():
    # Theorem 4.3: with a repeated top eigenvalue the derivative is the largest eigenvalue of
    # U1^* X U1; any orthonormal basis of the eigenspace gives the same value
    rng = np.random.default_rng(9)
    s = MuStructure(3, 2)
    for _ in range(30):
        M = rng.normal(size=(5, 5)) + 1j * rng.normal(size=(5, 5))
        b = mixed_mu_upper(M, s, **TIGHT)
        lam = b.eigenvalues[0]
        if lam[1] > (1 - 1e-5) * lam[0]:
            break
    else:
        pytest.skip("no repeated top eigenvalue found")
    d1 = beta_derivatives(M, b, 0)
    Q, _ = np.linalg.qr(rng.normal(size=(2, 2)) + 1j * rng.normal(size=(2, 2)))
    U = b.eigenvectors.copy()
    U[0, :, :2] = U[0, :, :2] @ Q
    rotated = type(b)(b.beta, b.d, b.g, b.eigenvalues, U)
    assert np.allclose(beta_derivatives(M, rotated, 0), d1, rtol=1e-8, atol=1e-12)
    # one-sided: the bound after shrinking is no lower than the first-order prediction allows
    for i in range(5):
        h = 1e-4
        after = mixed_mu_upper(shrunk(M, i, h), s, **TIGHT).beta[0]
        assert after <= b.beta[0] + 1e-9
