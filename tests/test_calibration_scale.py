"""The sensors' calibration as one scale per output on the residues (issue 26), against brute force."""

import itertools

import numpy as np
import pytest

from setmem_hil.identification.calibration_scale import measured_scale_prior, plant_bounds, ratio_scale
from setmem_hil.model.modal_model import B0, B1, IntervalModel
from setmem_hil.model.prior import ModePrior, Prior


def test_the_ratio_scale_holds_every_corner_of_the_two_calibrations():
    e_f, e_y = 0.01, 0.02
    lo, hi = ratio_scale(e_f, e_y)
    corners = [(1 + y) / (1 + f) for f, y in itertools.product((-e_f, e_f), (-e_y, e_y))]
    assert lo == pytest.approx(min(corners)) and hi == pytest.approx(max(corners))
    with pytest.raises(ValueError):
        ratio_scale(1.0, 0.0)


@pytest.mark.parametrize("seed", range(10))
def test_the_plant_bounds_hold_every_true_residue_the_measured_model_allows(seed):
    rng = np.random.default_rng(seed)
    lower = np.column_stack([rng.uniform(0.01, 0.1, 3), rng.uniform(1, 400, 3), rng.uniform(-2, 1, 3), rng.uniform(-5, 3, 3)])
    upper = lower + rng.uniform(0.0, 2.0, lower.shape)
    measured = IntervalModel(lower, upper)
    scale = ratio_scale(0.01, 0.015)
    plant = plant_bounds(measured, scale)
    assert np.array_equal(plant.lower[:, :2], measured.lower[:, :2])  # the poles are not scaled
    for _ in range(200):  # a measured residue b' = c b: the true b = b' / c must be inside
        c = rng.uniform(*scale)
        b = rng.uniform(measured.lower, measured.upper) / c
        assert np.all(plant.lower[:, [B1, B0]] <= b[:, [B1, B0]] + 1e-12)
        assert np.all(b[:, [B1, B0]] <= plant.upper[:, [B1, B0]] + 1e-12)


def test_the_measured_scale_prior_holds_c_times_the_prior_and_keeps_fixed_and_unbounded_residues():
    prior = Prior((ModePrior(0.9, 1.1, 0.5, b1_min=0.0, b1_max=0.0, b0_min=2.0, b0_max=5.0), ModePrior(5.0, 7.0, 0.5)))
    scale = ratio_scale(0.01, 0.01)
    scaled = measured_scale_prior(prior, scale)
    first, second = scaled.modes
    assert first.b1_min == first.b1_max == 0.0
    assert first.b0_min == pytest.approx(2.0 * scale[0]) and first.b0_max == pytest.approx(5.0 * scale[1])
    assert second.b0_min == -np.inf and second.b0_max == np.inf
    assert (first.omega_min, first.zeta_max) == (0.9, 0.5)


def test_a_campaign_on_miscalibrated_sensors_keeps_the_true_residues_inside_the_plant_bounds(tmp_path, monkeypatch):
    """Every ratio 1.5 % high (the sensors' calibration, within the declared 1 % + 1 %): the
    journal's plant bounds are the measured model's residues widened by the scale and hold the
    true beam's; the experiment's transient model is the model as measured."""
    import importlib.util
    from pathlib import Path

    import dataclasses

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.sim_backends.beam import beam_parameters

    spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
    helpers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    helpers.install_fast_analysis(monkeypatch)
    scale = ratio_scale(0.01, 0.01)

    class Miscalibrated(helpers.ForwardingExperiment):
        calibration_scales = (scale,)

        def __init__(self, inner):
            super().__init__(inner)
            self.models = []

        def measure(self, omega_rad_s):
            m = self.inner.measure(omega_rad_s)
            return dataclasses.replace(m, response=1.015 * m.response, bound=scale[1] * m.bound)

        def update_model(self, model):
            self.models.append(model)

    path = tmp_path / "cheap.toml"
    path.write_text(helpers.cheap_procedure_text(2))
    p = load_procedure(path)
    exp = Miscalibrated(helpers.simulated(p, p.seed))
    journal = Journal.create(tmp_path / "j.sqlite", procedure_text=p.source_text, procedure_name=p.name, seed=p.seed,
                             software_version="test", backend="test", strategy="mu")
    run_campaign(p, exp, journal)
    stored = journal.iterations()
    journal.close()
    truth = beam_parameters(3).values
    assert len(stored) == len(exp.models) >= 2
    for measured, record in zip(exp.models, stored):
        plant = plant_bounds(measured, scale)
        assert np.array_equal(record.lower, plant.lower) and np.array_equal(record.upper, plant.upper)
        assert np.all(record.lower[:, B0] <= truth[:, B0]) and np.all(truth[:, B0] <= record.upper[:, B0])
        assert np.all(record.lower[:, :2] <= truth[:, :2]) and np.all(truth[:, :2] <= record.upper[:, :2])


def test_tight_data_from_a_miscalibrated_sensor_exclude_the_truth_until_the_plant_bounds_widen_them():
    """One mode measured 1.8 % high with 0.1 % bounds: the model as measured excludes the true
    residue (the data say so), the plant bounds hold it, and the poles are not touched."""
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.model.frequency_data import FrequencyData
    from setmem_hil.model.modal_model import ModalParameters

    truth = ModalParameters.from_modal([6.27], [0.02], [3.0], [0.0])
    omega = np.array([5.0, 5.6, 6.0, 6.2, 6.4, 6.6, 7.0, 7.6])
    g = 1.018 * truth.frequency_response(omega)
    prior = Prior((ModePrior(5.41, 7.34, 0.5, b1_min=0.0, b1_max=0.0),))
    scale = ratio_scale(0.01, 0.01)
    measured = identify(FrequencyData(omega, g, 1e-3 * np.abs(g)), measured_scale_prior(prior, scale)).model
    plant = plant_bounds(measured, scale)
    b0 = truth.values[0, B0]
    assert not measured.lower[0, B0] <= b0 <= measured.upper[0, B0]
    assert plant.lower[0, B0] <= b0 <= plant.upper[0, B0]
    assert np.array_equal(plant.lower[:, :2], measured.lower[:, :2]) and np.array_equal(plant.upper[:, :2], measured.upper[:, :2])


@pytest.mark.parametrize("seed", range(5))
def test_the_uncertain_plant_with_a_common_gain_holds_every_gain_times_every_box_plant(seed):
    """A second formulation: for any k in the gain interval and any residues in the box, the
    output row ``k (C_mid + Delta C)`` is ``C + sum q_i l_i n_i`` with every ``|q_i| <= 1``."""
    from setmem_hil.robust.uncertain_plant import uncertain_plant

    rng = np.random.default_rng(seed)
    lower = np.column_stack([rng.uniform(0.01, 0.1, 3), rng.uniform(1, 400, 3), np.zeros(3), rng.uniform(0.5, 3, 3)])
    upper = lower + np.column_stack([rng.uniform(0, 0.02, 3), rng.uniform(0, 2, 3), np.zeros(3), rng.uniform(0, 1, 3)])
    model = IntervalModel(lower, upper)
    gain = (0.98, 1.02)
    plant = uncertain_plant(model, gain)
    assert plant.names[-1] == "gain" and plant.n_real == uncertain_plant(model).n_real + 1
    _, _, c_mid, _ = model.midpoint.state_space_matrices()
    rows = plant.E_c.ravel()[:, None] * plant.F_c  # each C parameter's row for q = 1
    k0, e = 1.0, 0.02
    mid, half = 0.5 * (lower[:, B0] + upper[:, B0]), 0.5 * (upper[:, B0] - lower[:, B0])
    free = half > 0
    for _ in range(50):
        k = rng.uniform(*gain)
        b0 = rng.uniform(lower[:, B0], upper[:, B0])
        target = np.zeros_like(np.ravel(c_mid))
        target[0::2] = k * b0
        delta = k / k0 - 1.0  # the offsets the module docstring names
        q = np.append(((1 + delta) * (b0 - mid) / np.where(free, half, 1.0) / (1 + e))[free], delta / e)
        assert np.all(np.abs(q) <= 1 + 1e-9)
        assert np.allclose(np.ravel(plant.C) + rows.T @ q, target, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
def test_mu_bar_with_a_common_gain_bounds_every_plant_of_the_set_and_costs_less_than_widening():
    """The claim checked plant by plant (the exact one-plant test of ``validate``): every
    vertex of a box times either end of the gain stays below the analysis's mu-bar; and one
    common gain costs less mu-bar than every residue widened independently by it."""
    from setmem_hil.io.procedure import default_procedure
    from setmem_hil.model.modal_model import ModalParameters
    from setmem_hil.robust.analysis import analyze_robust_performance
    from setmem_hil.robust.validation import box_plants, rp_peak
    from setmem_hil.sim_backends.beam import beam_parameters

    truth = beam_parameters(3).values
    spread = np.array([0.2, 0.003, 0.0, 0.04])  # relative half widths of a1, a0, b1, b0
    model = IntervalModel(truth * (1 - spread), truth * (1 + spread))
    weights = default_procedure().weights
    scale = ratio_scale(0.01, 0.01)
    gain = (1 / scale[1], 1 / scale[0])
    common = analyze_robust_performance(model, weights, gain=gain)
    K = common.controller  # one compensator for the three sets (each design would differ)
    widened = analyze_robust_performance(plant_bounds(model, scale), weights, controller=K)
    alone = analyze_robust_performance(model, weights, controller=K)
    assert alone.mu_peak <= common.mu_peak < widened.mu_peak
    grid = np.geomspace(common.omega.min(), common.omega.max(), 500)
    plants, _ = box_plants(model, 0)
    worst = 0.0
    for values in plants:
        for k in gain:
            scaled = values.copy()
            scaled[:, [B1, B0]] *= k
            worst = max(worst, rp_peak(ModalParameters(scaled), common.controller, weights, grid, refine=1)[0])
    assert worst <= common.mu_peak * (1 + 1e-6)


def test_validate_checks_the_box_as_measured_at_both_ends_of_the_gain():
    """``setmem-hil validate`` on an iteration with a common gain: the claimed set is every
    plant of the box as measured times each end of the gain, not the wider interval hull."""
    from types import SimpleNamespace

    from setmem_hil.cli.commands.validate import _claimed_set

    lower = np.array([[0.01, 0.9, 0.0, 3.0], [0.1, 39.0, 0.0, 3.5]])
    upper = np.array([[0.03, 1.1, 0.0, 5.0], [0.2, 40.0, 0.0, 4.5]])
    record = SimpleNamespace(k=2, lower=lower * 0.5, upper=upper * 2.0,  # the hull is not what is checked
                             common_gain={"gain": [0.98, 1.02], "lower": lower.tolist(), "upper": upper.tolist()})
    plants, drawn = _claimed_set(record, 0)
    assert plants.shape == (2 * 2 ** 6, 2, 4) and "2 gains" in drawn
    for k, half in zip((0.98, 1.02), np.split(plants, 2)):
        assert np.all((half[:, :, :2] >= lower[:, :2]) & (half[:, :, :2] <= upper[:, :2]))
        assert np.allclose(np.sort(np.unique(half[:, :, 3])), np.sort(np.unique(k * np.concatenate([lower[:, 3], upper[:, 3]]))))
