"""Monotone safeguard (thesis eq. 5.8-5.12) with a stand-in design/analysis of known behaviour."""

from dataclasses import dataclass

import numpy as np
import pytest

from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.design.safeguard import expanded_model, safeguarded_design


@dataclass(frozen=True)
class FakeController:
    design_mid: np.ndarray
    design_width: float


@dataclass(frozen=True)
class FakeAnalysis:
    mu_peak: float
    controller: FakeController


def bad_band_analysis(bad=(3.0, 7.0)):
    """mu = total width * (1 + |controller midpoint - model midpoint|_1) + 10 if the controller was
    designed for a total width inside ``bad``: a design method that is sometimes worse for less
    uncertainty, but obeys Lemma 2.2 for a fixed controller and nominal model."""

    def analyze(model, controller):
        if controller is None:
            controller = FakeController(model.midpoint.values.copy(), float(model.width.sum()))
        penalty = 10.0 if bad[0] <= controller.design_width <= bad[1] else 0.0
        shift = float(np.abs(controller.design_mid - model.midpoint.values).sum())
        return FakeAnalysis(float(model.width.sum()) * (1.0 + shift) + penalty, controller)

    return analyze


def box(lo, hi):
    return IntervalModel(np.array([lo], dtype=float), np.array([hi], dtype=float))


def test_expanded_box_is_centred_on_the_old_midpoint_and_between_new_and_old():
    old = box([0.0, 1.0, 0.0, 2.0], [0.4, 3.0, 0.0, 6.0])
    new = box([0.1, 2.0, 0.0, 2.5], [0.3, 2.8, 0.0, 3.5])
    phi = expanded_model(old.midpoint, new)
    assert np.allclose(phi.midpoint.values, old.midpoint.values)  # eq. 5.8
    assert np.all(phi.lower <= new.lower) and np.all(phi.upper >= new.upper)  # contains the new box
    assert np.all(phi.lower >= old.lower) and np.all(phi.upper <= old.upper)  # inside the old box
    # eq. 5.9: half-width = max distance from the old midpoint to a new bound
    assert phi.upper[0, 1] - 2.0 == pytest.approx(max(2.8 - 2.0, 2.0 - 2.0))
    assert phi.upper[0, 3] - 4.0 == pytest.approx(max(3.5 - 4.0, 4.0 - 2.5))
    with pytest.raises(ValueError, match="previous_midpoint"):
        expanded_model(np.zeros((2, 4)), new)


def test_first_iteration_and_improving_designs_take_the_new_design():
    analyze = bad_band_analysis()
    k1 = safeguarded_design(box([0, 0, 0, 0], [4, 4, 0, 4]), None, analyze)  # width 12
    assert k1.branch == "new-design" and k1.mu_peak == pytest.approx(12.0)
    k2 = safeguarded_design(box([0, 0, 0, 0], [1, 1, 0, 0.5]), k1, analyze)  # width 2.5: outside bad band
    assert k2.branch == "new-design" and k2.mu_peak == pytest.approx(2.5)


def test_worse_new_design_falls_back_to_the_expanded_box():
    analyze = bad_band_analysis(bad=(2.0, 3.0))
    k1 = safeguarded_design(box([0, 0, 0, 0], [4, 4, 0, 4]), None, analyze)  # mid (2,2,0,2), width 12
    new = box([0, 0, 0, 0], [1, 1, 0, 0.5])  # width 2.5 -> in the bad band: 12.5 > 12
    k2 = safeguarded_design(new, k1, analyze)
    # expanded about (2,2,0,2): half-widths 2, 2, 0, 2 -> width 12 (outside the bad band) -> mu 12
    assert k2.tried["new-design"] == pytest.approx(12.5)
    assert k2.branch == "expanded"
    assert k2.mu_peak == pytest.approx(12.0)
    assert np.allclose(k2.analysis_model.midpoint.values, k1.analysis_model.midpoint.values)


def test_previous_controller_when_both_redesigns_are_worse():
    analyze = bad_band_analysis(bad=(3.0, 7.0))
    k1 = safeguarded_design(box([0, 0, 0, 0], [4, 4, 0, 2]), None, analyze)  # width 10, mid (2,2,0,1)
    new = box([1.5, 1.5, 0, 0.5], [3.0, 2.5, 0, 1.5])  # width 3.5: bad
    # expanded about (2, 2, 0, 1): half-widths max(1, .5), max(.5, .5), 0, max(.5, .5) -> width 4: bad
    k2 = safeguarded_design(new, k1, analyze)
    assert k2.tried["new-design"] > k1.mu_peak and k2.tried["expanded"] > k1.mu_peak
    assert k2.branch == "previous-controller"
    assert k2.analysis.controller is k1.analysis.controller
    # Lemma 2.2 with the old controller and old nominal: mu = width of the expanded box
    assert k2.mu_peak == pytest.approx(4.0)


def test_reported_mu_never_increases_over_random_shrinking_sequences():
    rng = np.random.default_rng(7)
    analyze = bad_band_analysis(bad=(1.0, 6.0))
    lo, hi = np.zeros((1, 4)), np.full((1, 4), 3.0)
    outcome = None
    mus = []
    for _ in range(25):
        # shrink each side by a random fraction (bounds never loosen, eq. 5.4-5.5)
        w = hi - lo
        lo = lo + rng.uniform(0, 0.3, size=lo.shape) * w
        hi = hi - rng.uniform(0, 0.3, size=hi.shape) * (hi - lo)
        outcome = safeguarded_design(IntervalModel(lo.copy(), hi.copy()), outcome, analyze)
        mus.append(outcome.mu_peak)
    assert np.all(np.diff(mus) <= 1e-12)
