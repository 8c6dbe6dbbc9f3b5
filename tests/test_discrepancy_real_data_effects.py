"""Issue 14: residual terms as discrepancy candidates, and 'ambiguous' when two explain the data equally."""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.discrepancy.effects import CandidateFit
from setmem_hil.discrepancy.workflow import ambiguous_alternative, discrepancy_from_prior, discriminating_frequency
from setmem_hil.io.procedure import thesis_beam_prior
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.sim_backends.beam import beam_parameters

TRUTH = beam_parameters().truncated(3)


def test_hidden_mass_line_is_named_residual_mass_with_its_interval():
    w = np.geomspace(0.3, 30.0, 80)
    r_true = 0.3
    g = TRUTH.frequency_response(w) - r_true / w**2
    bound = 0.01 * np.abs(g) + 1e-3
    rng = np.random.default_rng(1)
    g = g + 0.5 * bound * np.sqrt(rng.uniform(size=w.size)) * np.exp(2j * np.pi * rng.uniform(size=w.size))
    doc = discrepancy_from_prior(FrequencyData(w, g, bound), thesis_beam_prior()).to_document()
    (effect,) = doc["effects"]
    assert effect["name"] == "residual_mass"
    lo, hi = effect["params"]["r_interval"]
    assert lo <= r_true <= hi
    assert doc["after"]["max_normalized_residual"] <= 1.0 < doc["before"]["max_normalized_residual"]


def _fit(name: str, residual: float, params: dict, n: int = 1, response=None) -> CandidateFit:
    fit = CandidateFit(name, n, residual, np.array([residual]), np.zeros(12), 3, params)
    if response is not None:
        object.__setattr__(fit, "response", response)
    return fit


def test_equal_candidates_are_ambiguous_and_unequal_ones_are_not():
    fits = {"none": _fit("none", 5.0, {}, 0), "feedthrough": _fit("feedthrough", 0.80, {"d": 1.0}),
            "residual_mass": _fit("residual_mass", 0.82, {"r": 2.0}), "time_delay": _fit("time_delay", 3.0, {"tau": 0.1})}
    assert ambiguous_alternative(fits, "feedthrough", 1.0, 30.0) == "residual_mass"
    fits["residual_mass"] = _fit("residual_mass", 0.95, {"r": 2.0})  # 0.15 apart: the better one wins
    assert ambiguous_alternative(fits, "feedthrough", 1.0, 30.0) is None
    fits["extra_mode"] = _fit("extra_mode", 0.80, {}, n=3)  # more parameters: never a rival
    assert ambiguous_alternative(fits, "feedthrough", 1.0, 30.0) is None


def test_discriminating_frequency_is_where_the_structures_differ_most_against_the_bound():
    w = np.geomspace(1.0, 10.0, 30)
    data = FrequencyData(w, np.zeros(w.size, complex), np.full(w.size, 0.1))
    w0 = 3.0  # constant d = 1 and mass line r / w^2 with r = w0^2 agree at w0, differ most at the lowest frequency
    a = _fit("feedthrough", 0.5, {"d": 1.0}, response=lambda x: np.ones_like(np.asarray(x, float)) + 0j)
    b = _fit("residual_mass", 0.5, {"r": w0**2}, response=lambda x: w0**2 / np.asarray(x, float) ** 2 + 0j)
    assert discriminating_frequency(data, a, b) == pytest.approx(1.0 / 1.5, rel=1e-9)
