"""Property tests of the one-mode identification on random systems (issue 2)."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.identification.algorithm import identify
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.model.prior import ModePrior, Prior
from setmem_hil.sim_backends.noise import bounded_complex_noise


@st.composite
def one_mode_case(draw):
    omega_n = 10 ** draw(st.floats(-1.5, 2.5))  # four decades
    zeta = draw(st.floats(0.002, 0.2))
    b0 = draw(st.floats(0.5, 50.0)) * draw(st.sampled_from([-1.0, 1.0]))
    b1 = draw(st.floats(-1.0, 1.0)) * omega_n * 0.05 * draw(st.sampled_from([0.0, 1.0]))
    snr = 10 ** draw(st.floats(0.5, 2.0))  # peak signal-to-noise ratio
    n_points = draw(st.integers(4, 9))
    spread = draw(st.floats(0.3, 3.0))  # points within +- spread * half-power bandwidths
    seed = draw(st.integers(0, 2**31 - 1))
    return omega_n, zeta, b0, b1, snr, n_points, spread, seed


def make(case):
    omega_n, zeta, b0, b1, snr, n_points, spread, seed = case
    truth = ModalParameters.from_modal([omega_n], [zeta], [b0], [b1])
    rng = np.random.default_rng(seed)
    w = omega_n * (1 + zeta * spread * rng.uniform(-1, 1, n_points))
    w = np.sort(np.abs(w)) + 1e-9
    peak = abs(b0) / (2 * zeta * omega_n**2)
    bound = np.full(w.size, peak / snr)
    g = truth.frequency_response(w) + bounded_complex_noise(bound, rng)
    prior = Prior((ModePrior(omega_n * 0.8, omega_n * 1.25, 0.5, b1_min=-abs(b1) - omega_n, b1_max=abs(b1) + omega_n),))
    return truth, FrequencyData(w, g, bound), prior


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(one_mode_case())
def test_truth_always_inside_the_box(case):
    truth, data, prior = make(case)
    result = identify(data, prior)
    assert result.model.contains(truth).all(), (result.model.lower, result.model.upper, truth.values)
    for gamma, partitioned in zip(result.embedding_gamma, result.partitioned):
        if partitioned:
            assert gamma <= prior.gamma + 1e-9


def test_a_lone_mode_on_the_tight_path_with_four_points_near_its_peak():
    """Hypothesis's find (stop 67): a lone lightly damped mode (zeta 0.002, four points within a
    third of a half-power bandwidth, peak SNR 3.2) sent the one-mode result to the close-mode
    machinery as a group of one, whose choice of the modes to multiply through asked for a second
    mode (IndexError). With that fixed, the ValueError of the group search's empty concatenation
    was read as a proof that the data were inconsistent (exit 3) although the truth fits them; and
    the witness search's own starts missed the mode's thin feasible set. Truth: the mode's own
    parameters inside the box, and a witness that fits (the truth's misfit is below 1 here)."""
    truth, data, prior = make((8.058421877614817, 0.002, -0.5, 0.0, 3.1622776601683795, 4, 0.3125, 0))
    assert np.all(np.abs(truth.frequency_response(data.omega_rad_s) - data.response) <= data.bound)
    result = identify(data, prior)
    assert result.model.contains(truth).all()
    assert result.witness.fits and result.verified.all()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(one_mode_case(), st.floats(-1.0, 1.0))
def test_adding_a_point_never_widens_the_box(case, where):
    """With the previous bounds given (eq. 5.4-5.5), as the campaign loop does. Without them the
    box can widen by ~1% of a width: the partition plan depends on the path of the iterations."""
    truth, data, prior = make(case)
    first = identify(data, prior)
    omega_n, zeta = truth.natural_frequencies[0], truth.damping_ratios[0]
    w_new = omega_n * (1 + 2 * zeta * where)
    rng = np.random.default_rng(case[-1] + 1)
    extra = FrequencyData([w_new], truth.frequency_response([w_new]) + bounded_complex_noise(data.bound[:1], rng), data.bound[:1])
    second = identify(data.appended(extra), prior, previous=first.model)
    assert np.all(second.model.lower >= first.model.lower)
    assert np.all(second.model.upper <= first.model.upper)
    assert second.model.contains(truth).all()

