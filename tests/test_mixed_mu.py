"""Mixed-mu upper bound (Definition 2.2 / Lemma 2.1) against independent truths."""

import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

from setmem_hil.robust.mixed_mu import MuStructure, bound_at_scalings, mixed_mu_upper, scaled_hermitian
from setmem_hil.robust.mixed_mu_lmi import mixed_mu_upper_lmi
from setmem_hil.robust.mu_lower_bound import mixed_mu_lower

PRECISE = dict(tol=1e-7, max_iter=300)


def random_complex(rng, n, k=1):
    return rng.normal(size=(k, n, n)) + 1j * rng.normal(size=(k, n, n))


def test_purely_complex_equals_optimal_d_scaled_sigma_max():
    rng = np.random.default_rng(11)
    M = random_complex(rng, 4, 3)
    s = MuStructure(0, 4)
    ours = mixed_mu_upper(M, s, **PRECISE).beta
    for k in range(3):
        # log sigma_max(D M D^-1) is convex in log D: a plain minimiser finds the optimum
        f = lambda y: np.linalg.norm(np.exp(np.r_[0.0, y])[:, None] * M[k] / np.exp(np.r_[0.0, y])[None, :], 2)
        best = min(minimize(f, np.zeros(3), method="Nelder-Mead", options=dict(xatol=1e-10, fatol=1e-12, maxiter=20000)).fun
                   for _ in range(1))
        assert ours[k] == pytest.approx(best, rel=1e-5)
        assert ours[k] <= best * (1 + 1e-6)


def rank_one_mu(a, b, p):
    """Closed-form mixed mu of ``a b^*`` (real blocks first): ``min_x sum_R |Re c + x Im c| + sum_C |c| sqrt(1+x^2)``."""
    c = a * np.conj(b)
    f = lambda x: np.abs(c[:p].real + x * c[:p].imag).sum() + np.abs(c[p:]).sum() * np.sqrt(1 + x * x)
    # convex piecewise-smooth in x: bracket by the kinks and polish
    kinks = [-c[i].real / c[i].imag for i in range(p) if abs(c[i].imag) > 1e-14]
    cands = [minimize_scalar(f, bounds=(lo, hi), method="bounded", options=dict(xatol=1e-13)).fun
             for lo, hi in zip([-1e3] + sorted(kinks), sorted(kinks) + [1e3])]
    return min(cands + [f(x) for x in kinks])


@pytest.mark.parametrize("seed,p,n", [(1, 2, 4), (2, 3, 5), (3, 1, 3), (4, 4, 6)])  # (4, 4, 6): a ray optimum
def test_rank_one_matches_closed_form(seed, p, n):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=n) + 1j * rng.normal(size=n)
    b = rng.normal(size=n) + 1j * rng.normal(size=n)
    M = np.outer(a, np.conj(b))
    truth = rank_one_mu(a, b, p)
    ours = mixed_mu_upper(M, MuStructure(p, n - p), **PRECISE).beta[0]
    assert ours >= truth * (1 - 1e-9)  # an upper bound on mu (mu = bound for rank one)
    assert ours == pytest.approx(truth, rel=1e-3)
    lower = mixed_mu_lower(M, MuStructure(p, n - p)).beta[0]
    assert lower <= truth * (1 + 1e-9)


@pytest.mark.slow
def test_upper_at_least_lower_and_certificates_hold():
    rng = np.random.default_rng(5)
    s = MuStructure(3, 2)
    M = random_complex(rng, 5, 20)
    up = mixed_mu_upper(M, s)
    lo = mixed_mu_lower(M, s)
    assert np.all(lo.beta <= up.beta * (1 + 1e-9))
    assert np.all(lo.beta > 0)
    # the lower bound is attained: det(I - M Delta / beta) = 0 with Delta in the unit ball
    for k in range(20):
        D = np.diag(lo.delta[k])
        assert np.all(np.abs(lo.delta[k]) <= 1 + 1e-12)
        assert np.all(np.abs(lo.delta[k][:3].imag) <= 1e-12)  # real blocks real
        assert abs(np.linalg.det(np.eye(5) - M[k] @ D / lo.beta[k])) < 1e-6 * np.linalg.norm(M[k], 2) ** 5
    # Lemma 2.1 certificate: M^* D_L M + j(G_L M - M^* G_L) - beta^2 D_L <= 0
    for k in range(20):
        DL, GL = np.diag(up.lmi_d[k]), np.diag(up.lmi_g[k])
        X = M[k].conj().T @ DL @ M[k] + 1j * (GL @ M[k] - M[k].conj().T @ GL) - up.beta[k] ** 2 * DL
        assert np.linalg.eigvalsh(X)[-1] <= 1e-9 * up.beta[k] ** 2 * up.lmi_d[k].max()
    # and beta is exactly lambda_max at the returned scalings
    assert np.allclose(bound_at_scalings(M, up.d, up.g), up.beta, rtol=1e-12)
    H = scaled_hermitian(M, up.d, up.g)
    assert np.allclose(np.linalg.eigvalsh(H)[:, -1], up.eigenvalues[:, 0], rtol=1e-10)


def test_lemma_2_2_shrinking_an_uncertainty_never_raises_the_bound():
    rng = np.random.default_rng(7)
    s = MuStructure(4, 2)
    M = random_complex(rng, 6, 8)
    base = mixed_mu_upper(M, s, **PRECISE).beta
    for j in range(6):
        A = np.ones(6)
        A[j] = 1 - rng.uniform(0.05, 0.9)
        AMA = A[None, :, None] * M * A[None, None, :]
        shrunk = mixed_mu_upper(AMA, s, **PRECISE).beta
        assert np.all(shrunk <= base * (1 + 1e-5))


def test_agrees_with_clarabel_lmi_reference():
    rng = np.random.default_rng(3)
    s = MuStructure(2, 2)
    M = random_complex(rng, 4, 3)
    ours = mixed_mu_upper(M, s, **PRECISE).beta
    for k in range(3):
        ref, d, g = mixed_mu_upper_lmi(M[k], s)
        assert ours[k] <= ref * (1 + 1e-4)
        assert ours[k] >= ref * (1 - 1e-4)


def test_input_checks():
    with pytest.raises(ValueError, match="expected shape"):
        mixed_mu_upper(np.eye(3), MuStructure(1, 1))
    with pytest.raises(ValueError, match="n_real"):
        MuStructure(0, 0)
