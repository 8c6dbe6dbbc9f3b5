"""Any frequency and magnitude scale (issue 18): rescaling time or units changes nothing physical.

The same beam with every frequency times S, the weights time-scaled (W(s) -> W(s/S)) and the same
relative noise must give the same mu-bar and sensitivities, peak frequencies times S, and the
same experiments (times S) in a campaign. The reference is the unscaled problem computed by the
same code; the rescaling itself is checked against direct evaluation (polynomials, responses).
"""

from __future__ import annotations

import numpy as np
import pytest

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure import default_procedure
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import THESIS_WEIGHTS
from setmem_hil.robust.analysis import analyze_robust_performance
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

TRUTH = beam_parameters().truncated(3)
# a model like the campaign's first iterations: +-20% damping, +-3% stiffness, +-15% residue
BOX = IntervalModel(*np.sort(np.stack([TRUTH.values * np.array([0.8, 0.97, 1.0, 0.85]),
                                       TRUTH.values * np.array([1.2, 1.03, 1.0, 1.15])]), axis=0))


def test_time_scaled_weights_are_w_of_s_over_S():
    w = np.geomspace(0.01, 1e4, 50)
    for S in (1e-2, 3.7, 314.159, 1e4):
        scaled = THESIS_WEIGHTS.time_scaled(S)
        s = 1j * w * S
        for num, den, num0, den0 in ((scaled.w1_num, scaled.w1_den, THESIS_WEIGHTS.w1_num, THESIS_WEIGHTS.w1_den),
                                     (scaled.w2_num, scaled.w2_den, THESIS_WEIGHTS.w2_num, THESIS_WEIGHTS.w2_den)):
            direct = np.polyval(num0, s / S) / np.polyval(den0, s / S)
            np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s), direct, rtol=1e-12)
        assert scaled.reference_frequency_rad_s() == pytest.approx(S, rel=1e-14)
        assert scaled.reference_magnitude() == pytest.approx(1.0, rel=1e-12)
    assert THESIS_WEIGHTS.reference_frequency_rad_s() == 1.0 and THESIS_WEIGHTS.reference_magnitude() == 1.0


def test_time_scaled_model_is_g_of_s_over_S():
    w = np.geomspace(0.1, 100, 40)
    for S in (1e-2, 311.0, 1e4):
        scaled = BOX.time_scaled(S)
        for params, params0 in ((scaled.midpoint, BOX.midpoint), (scaled.sample(np.ones((3, 4))), BOX.sample(np.ones((3, 4))))):
            np.testing.assert_allclose(params.frequency_response(w * S), params0.frequency_response(w), rtol=1e-12)


@pytest.fixture(scope="module")
def reference_analysis():
    return analyze_robust_performance(BOX, THESIS_WEIGHTS)


@pytest.mark.parametrize("S", [1e-2, 10.0, 314.159, 1e3, 1e4])
def test_analysis_is_time_scale_invariant(reference_analysis, S):
    ref = reference_analysis
    r = analyze_robust_performance(BOX.time_scaled(S), THESIS_WEIGHTS.time_scaled(S))
    assert r.mu_peak == pytest.approx(ref.mu_peak, rel=1e-6)
    # the band certificate (issue 27) adds points where the Hamiltonian crossings fall, which
    # move in the 9th digit with the scale; a peak found there is located to that accuracy
    assert r.mu_peak_omega == pytest.approx(ref.mu_peak_omega * S, rel=1e-7)
    assert r.mu_peak_certified and ref.mu_peak_certified
    assert set(r.sensitivities) == set(ref.sensitivities)
    for name, value in ref.sensitivities.items():
        assert r.sensitivities[name] == pytest.approx(value, rel=1e-5, abs=1e-8), name
    # the controller is the unscaled one, time-scaled: K_S(j w S) = K(j w)
    w = np.array([0.5, 3.9, 20.0])
    k_ref = np.squeeze(ref.controller(1j * w))
    k_s = np.squeeze(r.controller(1j * w * S))
    np.testing.assert_allclose(k_s, k_ref, rtol=1e-4)


@pytest.mark.parametrize("m", [1e-6, 1e6])
def test_analysis_is_magnitude_invariant(reference_analysis, m):
    """A receptance in other units (times m), with W1 (plant units) times m: same mu-bar."""
    ref = reference_analysis
    r = analyze_robust_performance(BOX.magnitude_scaled(m), THESIS_WEIGHTS.magnitude_scaled(m))
    assert r.mu_peak == pytest.approx(ref.mu_peak, rel=1e-6)
    assert r.mu_peak_omega == pytest.approx(ref.mu_peak_omega, rel=1e-7)  # see above
    for name, value in ref.sensitivities.items():
        assert r.sensitivities[name] == pytest.approx(value, rel=1e-5, abs=1e-8), name


def test_scaled_simulated_beam_measures_the_thesis_beam_at_omega_over_S():
    S = 314.159
    weights = THESIS_WEIGHTS.time_scaled(S)
    ref = SimulatedBeamExperiment(seed=4)
    scaled = SimulatedBeamExperiment(seed=4, first_mode_rad_s=S, w1_num=weights.w1_num, w1_den=weights.w1_den)
    np.testing.assert_allclose(scaled.truth.natural_frequencies, ref.truth.natural_frequencies * S, rtol=1e-12)
    for w in (0.8, 1.0, 6.3, 40.0):
        a, b = ref.measure(w), scaled.measure(w * S)
        assert b.response == pytest.approx(a.response, rel=1e-9)
        assert b.bound == pytest.approx(a.bound, rel=1e-9)


def _campaign(S: float, design: str = "h2"):
    procedure = default_procedure() if S == 1.0 else default_procedure().time_scaled(S)
    with open_experiment(procedure, procedure.seed) as experiment:
        return run_campaign(procedure, experiment, design=design)


@pytest.fixture(scope="module")
def reference_campaign():
    return _campaign(1.0)


@pytest.mark.slow
@pytest.mark.parametrize("S", [1e-2, 314.159, 1e4])
def test_campaign_makes_the_same_experiments_times_S(reference_campaign, S):
    """Issue 18's done-when: the 6.3.2 campaign at 50 Hz (and far beyond) reaches mu-bar < 1 with
    the same inputs x S and the same mu-bar per iteration. The H2 loop: the analysis it runs on
    is scale-invariant to rounding; the robust design's tuning (a long nonconvex descent) turns
    rounding into percent-level differences, so it gets the weaker test below."""
    ref, scaled = reference_campaign, _campaign(S)
    assert scaled.reached_goal and ref.reached_goal
    assert scaled.experiments_added == ref.experiments_added
    chosen = [it.next_omega for it in scaled.iterations]
    expected = [None if w is None else w * S for w in (it.next_omega for it in ref.iterations)]
    assert [w is None for w in chosen] == [w is None for w in expected]
    np.testing.assert_allclose([w for w in chosen if w is not None], [w for w in expected if w is not None], rtol=1e-9)
    np.testing.assert_allclose([it.mu_peak for it in scaled.iterations], [it.mu_peak for it in ref.iterations], rtol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("S", [314.159])
def test_the_robust_design_reaches_the_goal_at_any_frequency_scale(S):
    """Issue 38: the robust default keeps reaching mu-bar < 1 when the structure and weights are
    time-scaled (311 rad/s ~ 50 Hz): the tuning works in the analysis's normalised time. Issue 47:
    with the same choices and mu-bar within 1e-3 at every iteration (0.814 against 0.824 at the
    end before the design's inputs were cut to ten digits)."""
    scaled, ref = _campaign(S, design="robust"), _campaign(1.0, design="robust")
    assert scaled.reached_goal and scaled.final_mu_peak < 1.0
    assert scaled.experiments_added <= 3  # the thesis-scale robust loop needs 2 (docs/robust-design.md)
    assert all(it.design in ("robust", "h2") for it in scaled.iterations)
    assert len(scaled.iterations) == len(ref.iterations)
    for a, b in zip(ref.iterations, scaled.iterations):
        assert b.mu_peak == pytest.approx(a.mu_peak, rel=1e-3), (a.k, a.mu_peak, b.mu_peak)
        assert (a.next_omega is None) == (b.next_omega is None)
        if a.next_omega is not None:
            assert b.next_omega == pytest.approx(a.next_omega * S, rel=1e-9)


def test_first_mode_key_is_read_and_refused_for_loopback_fakes(tmp_path):
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.procedure_file import parse_procedure_text
    from pathlib import Path

    procedures = Path(__file__).resolve().parents[1] / "procedures"
    text = (procedures / "beam_6_3_2.toml").read_text().replace("[backend.simulation]", "[backend.simulation]\nfirst_mode_rad_s = 314.159", 1)
    assert parse_procedure_text(text, "x.toml").backend.simulation.first_mode_rad_s == 314.159
    serial = (procedures / "serial_loopback.toml").read_text()
    if "[backend.simulation]" not in serial:
        serial = serial.replace("[backend.transport]", "[backend.simulation]\nfirst_mode_rad_s = 2.0\n\n[backend.transport]", 1)
    else:
        serial = serial.replace("[backend.simulation]", "[backend.simulation]\nfirst_mode_rad_s = 2.0", 1)
    with pytest.raises(ProcedureError, match="first_mode_rad_s"):
        parse_procedure_text(serial, "x.toml")


def _mass_line_report(S: float, m: float):
    from setmem_hil.discrepancy.workflow import discrepancy_from_prior
    from setmem_hil.io.procedure import thesis_beam_prior
    from setmem_hil.model.frequency_data import FrequencyData

    w1 = np.geomspace(0.3, 30.0, 80)
    g = TRUTH.frequency_response(w1) - 0.3 / w1**2  # a hidden mass line
    bound = 0.01 * np.abs(g) + 1e-3
    rng = np.random.default_rng(1)
    g = g + 0.5 * bound * np.sqrt(rng.uniform(size=w1.size)) * np.exp(2j * np.pi * rng.uniform(size=w1.size))
    prior = thesis_beam_prior() if S == 1.0 else thesis_beam_prior().time_scaled(S)
    return discrepancy_from_prior(FrequencyData(w1 * S, g * m, bound * m), prior).to_document()


@pytest.mark.slow
@pytest.mark.parametrize("S, m", [(314.159, 1.0), (1.0, 1e-6), (1e-2, 1e6)])
def test_discrepancy_is_scale_invariant(S, m):
    ref, doc = _mass_line_report(1.0, 1.0), _mass_line_report(S, m)
    assert [e["name"] for e in doc["effects"]] == [e["name"] for e in ref["effects"]] == ["residual_mass"]
    assert doc["before"]["max_normalized_residual"] == pytest.approx(ref["before"]["max_normalized_residual"], rel=1e-6)
    assert doc["after"]["max_normalized_residual"] == pytest.approx(ref["after"]["max_normalized_residual"], rel=1e-6)
    r, r_ref = doc["effects"][0]["params"]["r"], ref["effects"][0]["params"]["r"]
    assert r == pytest.approx(r_ref * S * S * m, rel=1e-6)  # G + r/s^2: r scales like a0 b0 / a0


def test_the_robust_design_takes_the_same_path_whatever_the_rounding_of_its_inputs():
    """The robust tuning is a nonsmooth descent: a box changed by 1e-13 moved its mu-bar by 1e-3,
    and the 50 Hz campaign ended at 0.824 against 0.814 at 1 rad/s. Its inputs are now cut to ten
    digits (outwards for the box): the same box perturbed by rounding, and time-scaled to 50 Hz
    with the weights, give the same design."""
    from setmem_hil.robust.robust_design import TuningSettings

    tuning = TuningSettings(max_outer=1, inner_iterations=10)
    S = 314.159

    def mu(model, weights):
        return analyze_robust_performance(model, weights, design="robust", tuning=tuning).mu_peak

    reference = mu(BOX, THESIS_WEIGHTS)
    nudged = IntervalModel(BOX.lower * (1 - 3e-15), BOX.upper * (1 + 3e-15))
    assert mu(nudged, THESIS_WEIGHTS) == reference
    assert mu(BOX.time_scaled(S), THESIS_WEIGHTS.time_scaled(S)) == pytest.approx(reference, rel=1e-12)
