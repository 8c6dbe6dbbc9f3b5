"""Hidden-effect beam data: documented ranges, reproducibility, noise within the bound."""

import numpy as np
import pytest

from setmem_hil.discrepancy.workflow import DiscrepancySettings, discrepancy_from_prior
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.io.procedure import thesis_beam_prior
from setmem_hil.sim_backends import hidden_effects as he
from setmem_hil.sim_backends.beam import beam_parameters, fully_damped_magnitude


@pytest.mark.parametrize("effect", he.HIDDEN_EFFECTS)
def test_case_respects_documented_ranges(effect):
    case = he.draw_hidden_effect_case(effect, 3)
    w = case.data.omega_rad_s
    assert w.size == 78 and w.min() == pytest.approx(0.3) and w.max() == pytest.approx(40.0)
    assert he.NOISE_SCALE_RANGE[0] <= case.noise_scale <= he.NOISE_SCALE_RANGE[1]
    np.testing.assert_allclose(case.data.bound, case.noise_scale * fully_damped_magnitude(case.truth, w))
    clean = he.apply_effect(effect, case.params, case.truth.frequency_response(w), w)
    assert np.all(np.abs(case.data.response - clean) <= case.data.bound)
    p = case.params
    if effect == "time_delay":
        assert 5.0 <= np.degrees(p["tau"] * 40.0) <= 60.0
    elif effect == "first_order_lag":
        assert 3.0 <= 1.0 / p["tau"] <= 40.0
    elif effect == "extra_mode":
        assert any(a <= p["omega_n"] <= b for a, b in he.EXTRA_MODE_GAPS_RAD_S)
        assert 0.005 <= p["zeta"] <= 0.05
    if effect != "none":
        assert case.margin >= he.DETECTABLE_MARGIN


def test_same_seed_same_case():
    a = he.draw_hidden_effect_case("extra_mode", 9)
    b = he.draw_hidden_effect_case("extra_mode", 9)
    assert a.params == b.params
    np.testing.assert_array_equal(a.data.response, b.data.response)


def test_effect_outside_the_library_is_unexplained():
    """Two unmodelled modes: no single candidate explains them, so no name is forced."""
    rng = np.random.default_rng(5)
    truth = beam_parameters().truncated(3)
    w = he.hidden_effect_omegas(truth)
    bound = 0.1 * fully_damped_magnitude(truth, w)
    s = 1j * w
    g = truth.frequency_response(w)
    for wx, b0 in ((3.0, 0.2), (12.0, -1.0)):
        g = g + b0 / (s * s + 2 * 0.01 * wx * s + wx * wx)
    noise = bound * rng.uniform(size=w.size) * np.exp(2j * np.pi * rng.uniform(size=w.size))
    report = discrepancy_from_prior(FrequencyData(w, g + noise, bound), thesis_beam_prior(),
                                    DiscrepancySettings(inflation_steps=0, interval_steps=0))
    assert report.decision == "unexplained"
    assert [e["name"] for e in report.effects] == ["unexplained"]
    assert report.after["max_normalized_residual"] == report.before["max_normalized_residual"] > 1.0
