"""Discrepancy workflow on beam data with hidden effects (issue 6).

The truth of every case is known (the generator's effect and parameters), so the tests check
the named effect against it, the after-figures against the contract (worst normalised residual
<= 1.05, identification feasible), and the pieces against independent formulas.
"""

import numpy as np
import pytest

from setmem_hil.discrepancy.workflow import (
    DiscrepancySettings, check_discrepancy, choose_effect, disagreement_bands, discrepancy_from_prior, prior_from_model,
)
from setmem_hil.discrepancy.effects import CandidateFit
from setmem_hil.discrepancy.reidentify import extra_mode_prior, transform_data
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.io.procedure import thesis_beam_prior
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.hidden_effects import HIDDEN_EFFECTS, apply_effect, draw_hidden_effect_case

LEAN = DiscrepancySettings(inflation_steps=0, interval_steps=0)


def _fit(name, k, rho, **params):
    return CandidateFit(name, k, rho, np.array([rho]), np.zeros(12), 3, params)


def test_disagreement_bands_group_consecutive_points():
    w = np.array([5.0, 1.0, 2.0, 3.0, 4.0, 6.0, 7.0])
    rho = np.array([2.0, 0.5, 1.5, 1.2, 0.9, 3.0, 0.2])  # sorted: 1:.5 2:1.5 3:1.2 4:.9 5:2 6:3 7:.2
    assert disagreement_bands(w, rho) == ((2.0, 3.0), (5.0, 6.0))
    assert disagreement_bands(w, np.full(7, 1.0)) == ()


def test_rule_prefers_fewest_parameters_then_residual():
    fits = {"none": _fit("none", 0, 4.0), "time_delay": _fit("time_delay", 1, 0.99, tau=0.01),
            "feedthrough": _fit("feedthrough", 1, 0.9, d=1.0), "extra_mode": _fit("extra_mode", 3, 0.5)}
    assert choose_effect(fits, 1.0, 40.0) == "feedthrough"
    fits["none"] = _fit("none", 0, 0.999)
    assert choose_effect(fits, 1.0, 40.0) == "none"


def test_rule_says_unexplained_rather_than_forcing_a_name():
    fits = {"none": _fit("none", 0, 4.0), "time_delay": _fit("time_delay", 1, 1.3, tau=0.01),
            "extra_mode": _fit("extra_mode", 3, 1.01)}
    assert choose_effect(fits, 1.0, 40.0) == "unexplained"


def test_lag_with_corner_above_band_yields_to_delay():
    fits = {"none": _fit("none", 0, 4.0), "time_delay": _fit("time_delay", 1, 0.98, tau=0.005),
            "first_order_lag": _fit("first_order_lag", 1, 0.95, tau=0.005)}  # corner 200 rad/s > 40
    assert choose_effect(fits, 1.0, 40.0) == "time_delay"
    fits["first_order_lag"] = _fit("first_order_lag", 1, 0.95, tau=0.1)  # corner 10 rad/s, in band
    assert choose_effect(fits, 1.0, 40.0) == "first_order_lag"


@pytest.mark.parametrize("effect,value", [("time_delay", 0.012), ("first_order_lag", 0.08), ("feedthrough", 0.004)])
def test_transformed_bound_covers_every_value_in_the_interval(effect, value):
    """|g' - G3| <= R' for the true value anywhere within delta of the transform point."""
    rng = np.random.default_rng(11)
    truth = beam_parameters().truncated(3)
    w = np.geomspace(0.3, 40.0, 80)
    g3 = truth.frequency_response(w)
    R = 0.1 * np.abs(g3)
    key = "d" if effect == "feedthrough" else "tau"
    for true_value in value * np.array([0.7, 0.95, 1.0, 1.05, 1.3]):
        noise = R * rng.uniform(size=w.size) * np.exp(2j * np.pi * rng.uniform(size=w.size))
        data = FrequencyData(w, apply_effect(effect, {key: true_value}, g3, w) + noise, R)
        out = transform_data(effect, value, data, delta=abs(true_value - value))
        assert np.all(np.abs(out.response - g3) <= out.bound * (1 + 1e-12))


def test_extra_mode_prior_inserts_in_order_with_same_b1_rule():
    prior = thesis_beam_prior()
    new, k = extra_mode_prior(prior, 12.0, 0.1)
    assert k == 2 and new.n_modes == 4
    assert new.modes[2].omega_min == pytest.approx(10.8) and new.modes[2].omega_max == pytest.approx(13.2)
    assert new.modes[2].b1_min == new.modes[2].b1_max == 0.0
    assert [m.omega_min for m in new.modes] == sorted(m.omega_min for m in new.modes)


def test_prior_from_point_model_brackets_it():
    truth = beam_parameters().truncated(3)
    prior = prior_from_model(IntervalModel.point(truth))
    box = prior.initial_bounds()
    assert np.all(box.lower <= truth.values) and np.all(truth.values <= box.upper)
    np.testing.assert_allclose([m.omega_min for m in prior.modes], 0.9 * truth.natural_frequencies)
    assert all(m.b1_min == m.b1_max == 0.0 for m in prior.modes)


def test_inputs_are_not_modified():
    case = draw_hidden_effect_case("feedthrough", 5)
    model = IntervalModel.point(case.truth)
    copies = (case.data.response.copy(), case.data.bound.copy(), model.lower.copy())
    check_discrepancy(case.data, model, thesis_beam_prior(), LEAN)
    np.testing.assert_array_equal(case.data.response, copies[0])
    np.testing.assert_array_equal(case.data.bound, copies[1])
    np.testing.assert_array_equal(model.lower, copies[2])


def test_effect_parameter_interval_contains_the_truth():
    case = draw_hidden_effect_case("time_delay", 21)
    report = discrepancy_from_prior(case.data, thesis_beam_prior(), DiscrepancySettings(inflation_steps=0))
    assert report.decision == "time_delay"
    lo, hi = report.effects[0]["params"]["tau_interval"]
    assert lo <= case.params["tau"] <= hi
    assert report.after["feasible"] is True


def test_extra_mode_is_located_and_bounded():
    case = draw_hidden_effect_case("extra_mode", 22)
    report = discrepancy_from_prior(case.data, thesis_beam_prior(), LEAN)
    assert report.decision == "extra_mode"
    params = report.effects[0]["params"]
    assert params["omega_n"] == pytest.approx(case.params["omega_n"], rel=0.02)
    lo, hi = params["omega_n_interval"]
    assert lo <= case.params["omega_n"] <= hi
    # the disagreement bands before include the hidden mode's frequency neighbourhood
    assert any(a / 1.1 <= case.params["omega_n"] <= b * 1.1 for a, b in report.disagreement_bands)


# The statistical test: 4 hidden cases of each effect at random strengths and seeds, plus 6
# clean cases. Contract: right name in >= 90% of hidden cases, "none" in >= 95% of clean ones;
# after adding the effect, worst normalised residual <= 1.05 and identification feasible.
N_HIDDEN_PER_EFFECT = 4
N_CLEAN = 6


def _run_cases():
    outcomes = []
    for effect in HIDDEN_EFFECTS:
        n = N_CLEAN if effect == "none" else N_HIDDEN_PER_EFFECT
        for seed in range(n):
            case = draw_hidden_effect_case(effect, 7000 + 100 * HIDDEN_EFFECTS.index(effect) + seed)
            outcomes.append((case, discrepancy_from_prior(case.data, thesis_beam_prior(), LEAN)))
    return outcomes


@pytest.fixture(scope="module")
def outcomes():
    return _run_cases()


@pytest.mark.slow
def test_names_the_hidden_effect(outcomes):
    hidden = [(c, r) for c, r in outcomes if c.effect != "none"]
    right = sum(r.decision == c.effect for c, r in hidden)
    assert right >= 0.9 * len(hidden), [(c.effect, r.decision) for c, r in hidden if r.decision != c.effect]


@pytest.mark.slow
def test_clean_data_answer_none(outcomes):
    clean = [(c, r) for c, r in outcomes if c.effect == "none"]
    assert sum(r.decision == "none" and r.effects == () for c, r in clean) >= 0.95 * len(clean)


@pytest.mark.slow
def test_gap_shrinks_after_adding_the_effect(outcomes):
    for case, report in outcomes:
        if case.effect == "none" or report.decision != case.effect:
            continue
        assert report.before["max_normalized_residual"] > 1.0
        assert report.after["max_normalized_residual"] <= 1.05
        assert report.after["feasible"] is True
        assert report.disagreement_bands


@pytest.mark.slow
def test_document_has_the_contract_keys(outcomes):
    for case, report in outcomes[:: max(1, len(outcomes) // 5)]:
        doc = report.to_document()
        assert {"disagreement_bands", "effects", "before", "after"} <= set(doc)
        for key in ("before", "after"):
            assert isinstance(doc[key]["max_normalized_residual"], float)
            assert isinstance(doc[key]["feasible"], bool)
        for effect in doc["effects"]:
            assert {"name", "params", "evidence"} <= set(effect)
        if case.effect == "none":
            assert doc["effects"] == []
