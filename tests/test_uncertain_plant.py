"""Rank-one parametric uncertainty (eq. 6.2-6.12) and the augmented plant (eq. 6.16-6.23)."""

import numpy as np
import pytest

from setmem_hil.robust.augmented_plant import augmented_plant
from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.model.weights import THESIS_WEIGHTS

LOWER = [[0.01, 0.9, 0.0, 3.0], [0.05, 35.0, -0.2, -1.0]]
UPPER = [[0.05, 1.2, 0.0, 5.0], [0.30, 42.0, 0.1, 6.0]]


def test_names_order_and_fixed_parameters_absent():
    up = uncertain_plant(IntervalModel(LOWER, UPPER))
    # A-matrix parameters first (eq. 6.5-6.6), then C; b1 of mode 1 is fixed
    assert up.names == ("a1_1", "a0_1", "a1_2", "a0_2", "b0_1", "b1_2", "b0_2")
    assert up.n_a == 4 and up.n_real == 7
    assert np.allclose(up.half_widths, [0.02, 0.15, 0.125, 3.5, 1.0, 0.15, 3.5])


def test_rank_one_terms_have_equal_norms():
    up = uncertain_plant(IntervalModel(LOWER, UPPER))
    for i in range(up.n_a):
        assert np.linalg.norm(up.E_a[:, i]) == pytest.approx(np.linalg.norm(up.F_a[i]))
    for i in range(up.n_real - up.n_a):
        assert abs(up.E_c[0, i]) == pytest.approx(np.linalg.norm(up.F_c[i]))


def test_perturbations_span_the_interval_box():
    model = IntervalModel(LOWER, UPPER)
    up = uncertain_plant(model)
    rng = np.random.default_rng(4)
    for _ in range(5):
        q = rng.uniform(-1, 1, up.n_real)
        A, C = up.perturbed_matrices(q)
        # the same point built directly from parameter values mid + q * width / 2
        values = model.midpoint.values.copy()
        for qi, name, h in zip(q, up.names, up.half_widths):
            param, mode = name.split("_")
            values[int(mode) - 1, ("a1", "a0", "b1", "b0").index(param)] += qi * h
        A_ref, _, C_ref, _ = ModalParameters(values).state_space_matrices()
        assert np.allclose(A, A_ref) and np.allclose(C, C_ref)


def test_closing_the_real_blocks_gives_the_perturbed_plant():
    # upper LFT of the augmented plant with w_a = Q_a z_a, w_c = Q_c z_c and Delta_1 = Delta_2 = 0:
    # the channel u -> y must be the perturbed plant G_q(j omega)
    model = IntervalModel(LOWER, UPPER)
    up = uncertain_plant(model)
    P = augmented_plant(up, THESIS_WEIGHTS).to_statespace()
    rng = np.random.default_rng(8)
    q = rng.uniform(-1, 1, up.n_real)
    p = up.n_real
    omega = np.array([0.3, 1.0, 4.0, 6.3, 20.0])
    resp = P.frequency_response(omega)
    H = np.moveaxis(np.asarray(resp.frdata), -1, 0)  # (n_omega, outputs, inputs)
    for k, w in enumerate(omega):
        Pk = H[k]
        P11 = Pk[:p, :p]
        P12 = Pk[:p, -1:]
        P21 = Pk[-1:, :p]
        P22 = Pk[-1:, -1:]
        Q = np.diag(q)
        G = P22 + P21 @ Q @ np.linalg.solve(np.eye(p) - P11 @ Q, P12)
        A, C = up.perturbed_matrices(q)
        G_ref = C @ np.linalg.solve(1j * w * np.eye(A.shape[0]) - A, up.B)
        assert G[0, 0] == pytest.approx(G_ref[0, 0], rel=1e-9)


def test_weight_channels():
    # z_1 = W_1 u (additive uncertainty input) and z_2 = W_2 (y) with the extra pole
    up = uncertain_plant(IntervalModel(LOWER, UPPER))
    P = augmented_plant(up, THESIS_WEIGHTS).to_statespace()
    p = up.n_real
    w = np.array([0.5, 3.0, 40.0])
    H = np.moveaxis(np.asarray(P.frequency_response(w).frdata), -1, 0)
    s = 1j * w
    W1 = np.polyval(THESIS_WEIGHTS.w1_num, s) / np.polyval(THESIS_WEIGHTS.w1_den, s)
    n2, d2 = THESIS_WEIGHTS.w2_for_design()
    W2 = np.polyval(n2, s) / np.polyval(d2, s)
    G = H[:, -1, -1]
    assert np.allclose(H[:, p, -1], W1)  # u -> z_1
    assert np.allclose(H[:, p + 1, p + 1], W2)  # w_2 -> z_2 (open loop: y = w_2)
    assert np.allclose(H[:, p + 1, -1], W2 * G)  # u -> z_2
    assert np.allclose(H[:, -1, p], 1.0) and np.allclose(H[:, -1, p + 1], 1.0)  # w_1, w_2 -> y


def test_point_model_has_no_real_blocks():
    m = IntervalModel(LOWER, LOWER)
    up = uncertain_plant(m)
    assert up.n_real == 0
    P = augmented_plant(up, THESIS_WEIGHTS)
    assert P.n_real == 0 and P.n_w == 2
    with pytest.raises(ValueError, match="q: expected shape"):
        up.perturbed_matrices(np.zeros(3))
