"""The campaign hook on the thesis's simulated beam (8 modes, |W1| in the bound, section 6.2).

Modes 4-8 are unmodelled but covered by the bound, so a clean run must not raise a false
alarm; an effect hidden on top of the same data must still be named.
"""

import numpy as np
import pytest

from setmem_hil.discrepancy.workflow import check_discrepancy, discrepancy_from_prior
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.identification.algorithm import identify
from setmem_hil.io.procedure import thesis_6_3_2_initial_omegas, thesis_beam_prior
from setmem_hil.sim_backends.hidden_effects import apply_effect, hidden_effect_omegas
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment


def test_identified_model_on_thesis_beam_gives_no_false_alarm():
    beam = SimulatedBeamExperiment(seed=1, unmodelled_dynamics=True)
    omegas = list(thesis_6_3_2_initial_omegas()) + list(np.geomspace(0.3, 40.0, 20))
    data = FrequencyData.from_measurements(beam.measure_many(omegas))
    prior = thesis_beam_prior()
    model = identify(data, prior).model
    lower = model.lower.copy()
    report = check_discrepancy(data, model, prior)
    assert report.decision == "none" and report.effects == ()
    assert report.before["feasible"] is True and report.before["max_normalized_residual"] <= 1.0
    np.testing.assert_array_equal(model.lower, lower)  # the model is never changed
    doc = report.to_document()
    assert doc["effects"] == [] and doc["disagreement_bands"] == []


@pytest.mark.slow  # a campaign with discrepancy checks end to end (28 s)
def test_lag_hidden_in_eight_mode_beam_is_named():
    beam = SimulatedBeamExperiment(seed=3, unmodelled_dynamics=True)
    w = hidden_effect_omegas()
    data = FrequencyData.from_measurements(beam.measure_many(w))
    g3 = beam.modelled_truth.frequency_response(w)
    hidden = data.response + apply_effect("first_order_lag", {"tau": 0.1}, g3, w) - g3
    report = discrepancy_from_prior(FrequencyData(w, hidden, data.bound), thesis_beam_prior())
    assert report.decision == "first_order_lag"
    lo, hi = report.effects[0]["params"]["tau_interval"]
    assert lo <= 0.1 <= hi
    assert report.after["feasible"] is True and report.after["max_normalized_residual"] <= 1.0
