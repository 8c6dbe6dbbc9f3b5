"""Explicit Clarabel status translation in the conic layer (issue 12 item 6).

A solver result is never trusted by its status: ``AlmostSolved`` never yields a tight bound from
its primal point, ``AlmostPrimalInfeasible`` is never an infeasibility certificate, and a
``PrimalInfeasible`` whose certificate does not check keeps the box. Every reported bound comes
from a checked dual certificate or is the box's own bound, flagged unverified.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from setmem_hil.identification.embedding import embedding_bound
from setmem_hil.identification.one_mode_solver import OneModeProblem

TRUTH = np.array([0.02, 1.0, 0.0, 4.0])  # (a1, a0, b1, b0)


def problem():
    w = np.array([0.95, 0.99, 1.0, 1.01, 1.05])
    s = 1j * w
    g = TRUTH[3] / (s**2 + TRUTH[0] * s + TRUTH[1])
    R = 0.02 * np.abs(g)
    lo = np.array([0.0, 0.8, 0.0, 2.0])
    hi = np.array([0.2, 1.2, 0.0, 6.0])
    C = embedding_bound(w, R, lo[1], hi[1], hi[0])
    return OneModeProblem(w, g, lo, hi), C, lo, hi


def fake(status, n_points, n_free, x=None, z=None):
    return SimpleNamespace(status=status, x=np.zeros(n_free) if x is None else x,
                           z=np.zeros(3 * n_points + 2 * n_free) if z is None else z)


def test_real_solve_is_certified_and_tight():
    p, C, lo, hi = problem()
    sol = p.bound_box(C, lo, hi)
    assert sol.feasible and not sol.unverified
    free = p.free
    assert np.all(sol.lower[free] <= TRUTH[free]) and np.all(TRUTH[free] <= sol.upper[free])
    assert np.all(sol.upper[free] - sol.lower[free] < 0.5 * (hi[free] - lo[free]))
    assert set(p.last_certificates) == {(0, 1), (0, -1), (1, 1), (1, -1), (3, 1), (3, -1)}


@pytest.mark.parametrize("status", ["AlmostSolved", "MaxIterations", "NumericalError", "InsufficientProgress"])
def test_inaccurate_status_never_gives_a_tight_bound_from_its_primal_point(monkeypatch, status):
    p, C, lo, hi = problem()
    # the primal point claims every parameter sits exactly at the truth (a zero-width interval)
    y_truth = (TRUTH[p.free] - p.centre[p.free]) / p.half[p.free]
    monkeypatch.setattr(p, "_solve", lambda q, b, mode="default": fake(status, p.n_points, p.n_free, x=y_truth))
    sol = p.bound_box(C, lo, hi)
    assert sol.feasible
    # a zero dual certifies nothing beyond the box: the box's own bounds stand
    assert np.allclose(sol.lower[p.free], lo[p.free]) and np.allclose(sol.upper[p.free], hi[p.free])


@pytest.mark.parametrize("status", ["AlmostPrimalInfeasible", "PrimalInfeasible"])
def test_infeasibility_needs_a_checked_certificate(monkeypatch, status):
    p, C, lo, hi = problem()
    monkeypatch.setattr(p, "_solve", lambda q, b, mode="default": fake(status, p.n_points, p.n_free))
    sol = p.bound_box(C, lo, hi)
    assert sol.feasible  # a box holding the truth is never dropped on an unchecked status
    assert len(sol.unverified) == 2 * p.n_free
    assert all("box bound kept" in u for u in sol.unverified)


def test_almost_primal_infeasible_is_not_a_certificate_even_with_a_valid_farkas_vector(monkeypatch):
    """Solve an empty box for real, then relabel its status: still not accepted as empty."""
    p, C, lo, hi = problem()
    empty_lo, empty_hi = lo.copy(), hi.copy()
    empty_lo[1], empty_hi[1] = 1.15, 1.2  # a0 far from the truth 1.0: no consistent parameters
    real = p.bound_box(C, empty_lo, empty_hi)
    assert not real.feasible  # a genuine, checked PrimalInfeasible
    solve = OneModeProblem._solve

    def relabel(q, b, mode="default"):
        res = solve(p, q, b, mode)
        return SimpleNamespace(status="AlmostPrimalInfeasible" if str(res.status) == "PrimalInfeasible" else str(res.status),
                               x=res.x, z=res.z)

    monkeypatch.setattr(p, "_solve", relabel)
    assert p.bound_box(C, empty_lo, empty_hi).feasible


def test_unverified_bounds_reach_the_result_document(monkeypatch):
    from setmem_hil.identification import one_mode_solver
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.io.procedure import thesis_beam_prior
    from setmem_hil.sim_backends.thesis_cases import section_6_2_data

    monkeypatch.setattr(one_mode_solver.OneModeProblem, "_dual_soc", lambda self, res: None)
    data, beam = section_6_2_data(0)
    result = identify(data, thesis_beam_prior())
    assert result.model.contains(beam.modelled_truth).all()  # the box bounds are still valid
    doc = result.to_document()
    assert [m["verified"] for m in doc["modes"]] == [False] * 3
    assert all("unverified_reason" in m and "box bound kept" in m["unverified_reason"] for m in doc["modes"])
