"""The mixed-mu lower bound where the real blocks' interior matters (issue 38, item 3).

Truth: brute force on small problems (``det(I - M Delta)`` is affine in each block, so for three
real blocks the singular perturbations are found by a scan of one block and a closed-form
solve of the other two; for one real and one complex block by a scan of the real one), and the
two-cart benchmark of MATLAB's ``robstab`` documentation (``m1, m2, k = 1 +- 20 %``,
``C = 100 ((s + 1) / (0.001 s + 1))^3``, ``T = feedback(P C, 1)``): stability margin bounds
2.8826-2.8864 at 575 rad/s, i.e. mu between 0.3465 and 0.3469.
"""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.robust.augmented_plant import StateSpaceMatrices
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper
from setmem_hil.robust.mu_lower_bound import mixed_mu_lower


def _det_coefficients(M: np.ndarray, first: list[float]):
    """``det(I - M diag(first, d2, d3)) = a + b d2 + c d3 + e d2 d3``."""
    def det(d):
        return np.linalg.det(np.eye(M.shape[0]) - M * np.asarray(d, dtype=complex)[None, :])

    f00, f10, f01, f11 = (det([*first, x, y]) for x, y in ((0, 0), (1, 0), (0, 1), (1, 1)))
    return f00, f10 - f00, f01 - f00, f11 - f10 - f01 + f00


def brute_force_real_mu(M: np.ndarray, span: float = 5.0, n1: int = 241, n2: int = 2401) -> float:
    """``1 / min ||d||_inf`` over real ``d`` with ``det(I - M diag(d)) = 0`` (three real blocks):
    a grid over ``d1``; for each, the real roots in ``d2`` of ``Im d3(d2) = 0`` by bisection."""
    best = np.inf
    d2 = np.linspace(-span, span, n2)
    for d1 in np.linspace(-span, span, n1):
        a, b, c, e = _det_coefficients(M, [d1])

        def d3_of(x):
            return -(a + b * x) / (c + e * x)

        im = d3_of(d2).imag
        for i in np.flatnonzero(np.sign(im[:-1]) != np.sign(im[1:])):
            lo, hi = d2[i], d2[i + 1]
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if np.sign(d3_of(mid).imag) == np.sign(d3_of(lo).imag) else (lo, mid)
            x2 = 0.5 * (lo + hi)
            x3 = d3_of(x2)
            if abs(x3.imag) <= 1e-6 * max(1.0, abs(x3)):  # a root, not a pole of d3
                best = min(best, max(abs(d1), abs(x2), abs(x3.real)))
    return 1.0 / best


def brute_force_mixed_mu(M: np.ndarray, n: int = 200001) -> float:
    """One real block then one complex block: ``det = 1 - m11 d - m22 c + det(M) d c = 0`` gives
    ``c(d)``; ``mu = 1 / min_d max(|d|, |c(d)|)`` over a fine grid of real ``d``."""
    d = np.linspace(-20.0, 20.0, n)
    c = (1.0 - M[0, 0] * d) / (M[1, 1] - np.linalg.det(M) * d)
    return 1.0 / np.min(np.maximum(np.abs(d), np.abs(c)))


@pytest.mark.parametrize("seed", [1, 4, 7])
def test_three_real_blocks_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((3, 3)) + 1j * rng.standard_normal((3, 3))
    structure = MuStructure(3, 0)
    truth = brute_force_real_mu(M)  # a lower estimate of mu itself (the scan of d1 is a grid)
    lower = float(mixed_mu_lower(M, structure).beta[0])
    upper = float(mixed_mu_upper(M, structure).beta[0])
    assert lower <= upper * (1.0 + 1e-9)
    assert lower >= 0.98 * truth, (lower, truth, upper)


@pytest.mark.parametrize("seed", [2, 3])
def test_a_real_and_a_complex_block_against_brute_force(seed):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((2, 2)) + 1j * rng.standard_normal((2, 2))
    structure = MuStructure(1, 1)
    truth = brute_force_mixed_mu(M)
    lower = float(mixed_mu_lower(M, structure).beta[0])
    assert lower <= float(mixed_mu_upper(M, structure).beta[0]) * (1.0 + 1e-9)
    assert lower == pytest.approx(truth, rel=2e-3)


def _two_cart_closed_loop() -> StateSpaceMatrices:
    """``M(s)`` seen by ``diag(d_m1, d_m2, d_k)``: ``m = 1 + 0.2 d`` (``1/m`` as an LFT: ``v' = f -
    0.2 d v'``), ``k = 1 + 0.2 d_k``; ``u = -C y``, ``y = x2``."""
    import control

    s = control.tf("s")
    C = control.ss(100 * ((s + 1) / (0.001 * s + 1)) ** 3)
    Ac, Bc, Cc, Dc = (np.asarray(x, dtype=float) for x in (C.A, C.B, C.C, C.D))
    # states x1, v1, x2, v2; z = (v1', v2', x1 - x2)
    Ap = np.array([[0, 1, 0, 0], [-1, 0, 1, 0], [0, 0, 0, 1], [1, 0, -1, 0]], float)
    Bu = np.array([[0], [1], [0], [0]], float)
    Bw = np.array([[0, 0, 0], [-0.2, 0, -0.2], [0, 0, 0], [0, -0.2, 0.2]], float)
    Cz = np.array([[-1, 0, 1, 0], [1, 0, -1, 0], [1, 0, -1, 0]], float)
    Dzu = np.array([[1], [0], [0]], float)
    Dzw = np.array([[-0.2, 0, -0.2], [0, -0.2, 0.2], [0, 0, 0]], float)
    Cy = np.array([[0, 0, 1, 0]], float)
    A = np.block([[Ap - Bu @ Dc @ Cy, Bu @ Cc], [-Bc @ Cy, Ac]])
    B = np.vstack([Bw, np.zeros((Ac.shape[0], 3))])
    Cm = np.hstack([Cz - Dzu @ Dc @ Cy, Dzu @ Cc])
    assert np.max(np.linalg.eigvals(A).real) < 0.0  # the nominal loop is stable
    return StateSpaceMatrices(A, B, Cm, Dzw)


@pytest.mark.slow
def test_the_two_cart_benchmark_of_robstab():
    """MATLAB reports the critical frequency as 575 rad/s; real mu is discontinuous in frequency,
    and the destabilising perturbation makes the closed loop singular at 575.03 rad/s: found here
    as the frequency near 575 where the candidate eigenvalue is exactly real."""
    cl = _two_cart_closed_loop()
    structure = MuStructure(3, 0)
    grid = np.linspace(570.0, 580.0, 201)
    lower = mixed_mu_lower(cl.frequency_response(grid), structure).beta
    upper = mixed_mu_upper(cl.frequency_response(grid), structure).beta
    assert np.all(lower <= upper * (1.0 + 1e-9))
    assert upper.max() == pytest.approx(1.0 / 2.8826, rel=2e-3)  # robstab's upper bound on mu
    # the critical frequency between two grid points: bisection on the vertex eigenvalue's phase
    vertex = np.array([-1.0, -1.0, 1.0])

    def imag(w):
        lam = np.linalg.eigvals(cl.frequency_response([w])[0] * vertex[None, :])
        return lam[np.argmax(lam.real)].imag

    lo, hi = 570.0, 580.0
    assert np.sign(imag(lo)) != np.sign(imag(hi))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.sign(imag(mid)) == np.sign(imag(lo)) else (lo, mid)
    at_critical = float(mixed_mu_lower(cl.frequency_response([lo]), structure).beta[0])
    assert at_critical == pytest.approx(0.3465, rel=0.01)
