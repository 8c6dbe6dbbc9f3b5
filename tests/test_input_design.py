"""Input design: candidate sets, the line/ellipsoid estimate of eq. 4.49-4.52, ranking (5.3, 5.4.2)."""

import numpy as np
import pytest

from setmem_hil.design.input_design import (
    candidate_frequencies,
    closeness_score,
    improvement_from_widths,
    n_candidates,
    sensitivity_matrix,
    top_indices,
)
from setmem_hil.design.input_effects import estimate_input_effects
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.io.procedure import InputDesignSettings


def one_mode_box():
    # mode near 2 rad/s: a1 in [0.02, 0.2], a0 in [3.5, 4.5], b1 fixed 0, b0 in [2, 6]
    return IntervalModel(np.array([[0.02, 3.5, 0.0, 2.0]]), np.array([[0.2, 4.5, 0.0, 6.0]]))


def optimizers_through_midpoint(box):
    """Optimiser of each bound: the midpoint with that component moved to the bound."""
    mid = box.midpoint.values[0]
    opt = np.empty((1, 4, 2, 4))
    for j in range(4):
        for side, value in enumerate((box.lower[0, j], box.upper[0, j])):
            x = mid.copy()
            x[j] = value
            opt[0, j, side] = x
    opt[0, 2] = np.nan  # b1 is fixed
    return opt


def direct_constraint(x, omega, g, C):
    """Eq. 3.26 written out: |g (-w^2 + a1 j w + a0) - (b1 j w + b0)| <= C."""
    a1, a0, b1, b0 = x
    s = 1j * omega
    return abs(g * (s * s + a1 * s + a0) - (b1 * s + b0)) <= C


@pytest.mark.parametrize("omega", [1.5, 1.9, 2.05, 2.6])
def test_line_estimate_matches_brute_force_scan_of_the_constraint(omega):
    box = one_mode_box()
    opt = optimizers_through_midpoint(box)
    R = 0.05
    eff = estimate_input_effects(box, opt, [omega], [R])
    # independent: one mode, so E = R; C from eq. 3.26 by brute force over the a0 interval ends
    a1_hi = box.upper[0, 0]
    C = R * max(abs(-omega**2 + 1j * a1_hi * omega + a0) for a0 in (box.lower[0, 1], box.upper[0, 1]))
    mid = box.midpoint.values[0]
    s = 1j * omega
    g = mid[3] / (s * s + mid[0] * s + mid[1])  # certainty equivalence: the midpoint's response
    for j in (0, 1, 3):
        t = np.linspace(box.lower[0, j], box.upper[0, j], 20001)
        feasible = []
        for side in (0, 1):
            x = np.tile(opt[0, j, side], (t.size, 1))
            x[:, j] = t
            feasible.append(np.array([direct_constraint(xi, omega, g, C) for xi in x]))
        step = t[1] - t[0]
        # lower bound from the lower optimiser's line, upper bound from the upper optimiser's line
        assert eff.lower[0, 0, j] == pytest.approx(t[feasible[0]].min(), abs=1.5 * step)
        assert eff.upper[0, 0, j] == pytest.approx(t[feasible[1]].max(), abs=1.5 * step)
    # b1 is fixed: untouched
    assert eff.lower[0, 0, 2] == 0.0 and eff.upper[0, 0, 2] == 0.0


def test_estimates_never_loosen_and_closeness_flags_exactly_the_cut_bounds():
    box = one_mode_box()
    opt = optimizers_through_midpoint(box)
    omega = np.geomspace(0.3, 30.0, 200)
    eff = estimate_input_effects(box, opt, omega, 0.02 * np.ones_like(omega))
    assert np.all(eff.lower >= box.lower[None] - 1e-12)
    assert np.all(eff.upper <= box.upper[None] + 1e-12)
    assert np.all(eff.lower <= eff.upper)
    # closeness > 1 at the bound point <=> the line's feasible segment ends inside the interval
    free = [0, 1, 3]
    cut_hi = eff.upper[:, 0, free] < box.upper[0, free] - 1e-9
    cut_lo = eff.lower[:, 0, free] > box.lower[0, free] + 1e-9
    assert np.array_equal(cut_hi, eff.closeness[:, 0, free, 1] > 1.0)
    assert np.array_equal(cut_lo, eff.closeness[:, 0, free, 0] > 1.0)
    # near resonance the point is informative, far above it it is not
    assert cut_hi[np.argmin(abs(omega - 2.0))].any()
    assert not cut_hi[-1].any() and not cut_lo[-1].any()


def test_improvement_from_widths_follows_the_sensitivity_convention():
    old = np.array([[1.0, 4.0, 0.0, 2.0]])
    new = np.array([[0.25, 4.0, 0.0, 0.5]])
    s = np.array([[0.3, 0.2, 0.9, 0.5]])
    # eps_i = 1 - sqrt(new / old); b1 has zero width: no contribution
    expected = 0.3 * (1 - 0.5) + 0.2 * 0.0 + 0.5 * (1 - 0.5)
    assert improvement_from_widths(old, new, s, "mu") == pytest.approx(expected)
    assert improvement_from_widths(old, new, np.ones((1, 4)), "max-reduction") == pytest.approx(0.75 + 0.0 + 0.75)
    with pytest.raises(ValueError, match="scoring"):
        improvement_from_widths(old, new, s, "bogus")


def test_candidate_sets_grow_by_25_per_iteration_and_stay_in_band():
    settings = InputDesignSettings()
    assert n_candidates(1, settings) == 500
    assert n_candidates(4, settings) == 575
    w = candidate_frequencies(3, settings)
    assert w.size == 550
    assert w[0] == pytest.approx(0.1) and w[-1] == pytest.approx(1000.0)
    assert np.allclose(np.diff(np.log(w)), np.log(1e4) / 549)
    with pytest.raises(ValueError, match="iteration"):
        n_candidates(0, settings)


def test_sensitivity_matrix_reads_param_mode_keys():
    s = sensitivity_matrix({"b0_1": 0.8, "a1_3": 0.1, "b0_2": 0.75, "zeta_1": 5.0}, 3)
    assert s[0, 3] == 0.8 and s[1, 3] == 0.75 and s[2, 0] == 0.1
    assert s.sum() == pytest.approx(1.65)


def test_closeness_fallback_prefers_the_candidate_nearest_to_cutting_a_bound():
    box = one_mode_box()
    opt = optimizers_through_midpoint(box)
    # a large noise bound: nothing is cut anywhere, but the resonance comes closest
    omega = np.array([0.5, 1.9, 2.0, 8.0])
    eff = estimate_input_effects(box, opt, omega, 50.0 * np.ones(4))
    assert np.allclose(eff.width, box.width[None])
    score = closeness_score(eff, np.ones((1, 4)))
    assert np.all(score < 3.0 + 1e-12)
    best = top_indices(score, 1)[0]
    assert omega[best] in (1.9, 2.0)


def test_top_indices_orders_best_first_and_breaks_ties_by_index():
    assert top_indices(np.array([0.1, 0.5, 0.5, 0.2]), 3).tolist() == [1, 2, 3]


def test_a_candidate_seen_only_by_another_sensor_is_predicted_to_narrow_the_shared_poles():
    """Issue 25, item 3: a dwell reads every sensor, so the prediction adds a point to every
    output. The control sensor sits on mode 2's node (its residue there is zero), another sensor
    sees mode 2 fully: a dwell at mode 2's resonance can only narrow mode 2's poles through that
    other sensor. The control-only prediction must see (almost) nothing, the every-output one a
    large narrowing."""
    from setmem_hil.design.input_design import OtherOutputs
    from setmem_hil.identification.algorithm import IdentifySettings, identify, identify_outputs
    from setmem_hil.model.frequency_data import FrequencyData
    from setmem_hil.model.modal_model import ModalParameters
    from setmem_hil.model.prior import ModePrior, Prior

    truths = [ModalParameters(np.array([[0.04, 1.0, 0.0, 4.0], [0.25, 39.3, 0.0, b0]])) for b0 in (0.0, 4.0)]
    w = np.array([0.6, 0.8, 0.9, 1.1, 1.3, 3.0, 4.5, 9.0, 12.0])  # none near mode 2 (6.27 rad/s)
    rng = np.random.default_rng(5)
    datas = []
    for truth in truths:
        g = truth.frequency_response(w)
        bound = 0.05 * np.abs(g) + 1e-3
        datas.append(FrequencyData(w, g + 0.8 * bound * np.exp(2j * np.pi * rng.uniform(size=w.size)), bound))
    modes = lambda b0: Prior((ModePrior(0.884, 1.125, 0.5, 0.0, 0.0, 0.0, 10.0), ModePrior(5.41, 7.34, 0.5, 0.0, 0.0, *b0)))  # noqa: E731
    priors = [modes((-0.05, 0.05)), modes((0.0, 10.0))]
    joint = identify_outputs(datas, priors)
    control = joint.models[0]
    omega = np.array([6.27])
    bounds = tuple(np.array([0.05 * abs(t.frequency_response(omega)[0]) + 1e-3]) for t in truths)
    every = OtherOutputs(tuple(datas), tuple(priors), ("node", "tip"), tuple(joint.models), bounds)
    predicted_every = every.predicted_control_model(0, 6.27, IdentifySettings())
    nominal = control.midpoint.frequency_response(omega)
    predicted_control_only = identify(datas[0].appended(FrequencyData(omega, nominal, bounds[0])), priors[0], previous=control).model
    width = lambda m: m.upper[1, 1] - m.lower[1, 1]  # noqa: E731  (a0 of mode 2)
    assert width(predicted_control_only) > 0.9 * width(control)
    assert width(predicted_every) < 0.3 * width(control)


def test_a_floor_on_a_jointly_identified_mode_is_measured_before_what_the_split_promises():
    """Mode 3 of the thesis beam made to hold the floor (undamped, zero residue) with no
    prediction for it (its optimizers unknown, as for a mode identified in a group): alone, the
    choice follows chapter 4's promise elsewhere (mu-bar cannot fall below 1 anyway, but the
    predictions can see that mode); identified in a group, the floor mode's band is measured."""
    from dataclasses import replace

    from setmem_hil.design.input_design import choose_input, uniform_weights
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.io.procedure import thesis_beam_prior
    from setmem_hil.model.frequency_data import FrequencyData
    from setmem_hil.model.modal_model import A0, A1, B0
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    beam = SimulatedBeamExperiment(seed=1)
    prior = thesis_beam_prior()
    lines = [0.5, 0.99, 1.0, 1.01, 3.0, 6.2, 6.27, 6.33, 12.0, 17.4, 17.55, 17.7, 30.0]
    data = FrequencyData.from_measurements(beam.measure_many(lines))
    result = identify(data, prior)
    lo, hi = result.model.lower.copy(), result.model.upper.copy()
    lo[2, A1], lo[2, B0] = 0.0, -hi[2, B0]  # b1 is fixed at 0: the box now holds the floor
    optimizers = result.optimizers.copy()
    optimizers[2] = np.nan
    floored = replace(result, model=IntervalModel(lo, hi), optimizers=optimizers)
    omega = np.geomspace(0.1, 100.0, 300)
    bound = 0.02 * np.abs(floored.model.midpoint.frequency_response(omega)) + 1e-4
    half_width = 0.5 * hi[2, A1]
    band = (np.sqrt(lo[2, A0]) - half_width, np.sqrt(hi[2, A0]) + half_width)

    def choice(groups):
        return choose_input(replace(floored, groups=groups), data, prior, omega, bound, uniform_weights(floored.model),
                            scoring="max-reduction", exact_resolve_top=0, floor_modes=(3,)).next_omega_rad_s

    alone = choice(())
    assert not band[0] <= alone <= band[1]
    assert band[0] <= choice(((1, 2),)) <= band[1]
