"""Lemma 3.1 bound versus dense sampling of the parameter box (an independent computation)."""

import numpy as np

from setmem_hil.model.modal_model import IntervalModel, modal_response
from setmem_hil.identification.mode_mismatch import mode_mismatch_bounds


def test_bound_covers_sampled_boxes_and_is_attained_nearly():
    rng = np.random.default_rng(0)
    w = np.geomspace(0.1, 20, 40)
    tightness = []
    for trial in range(150):
        a0 = rng.uniform(0.5, 50)
        lo = np.array([[rng.uniform(0, 0.3), a0 * rng.uniform(0.7, 1), rng.uniform(-1, 0.5), rng.uniform(-5, 5)]])
        hi = lo + np.array([[rng.uniform(0, 0.5), a0 * rng.uniform(0, 0.5), rng.uniform(0, 1), rng.uniform(0, 8)]])
        if trial % 3 == 0:
            lo[0, 2] = hi[0, 2] = 0.0
        model = IntervalModel(lo, hi)
        bound = mode_mismatch_bounds(model, w)[0]
        corners = np.array([[lo[0, k] if (c >> k) & 1 == 0 else hi[0, k] for k in range(4)] for c in range(16)])
        samples = np.vstack([lo + rng.uniform(size=(2000, 4)) * (hi - lo), corners])
        distance = np.abs(modal_response(samples, w) - modal_response(model.midpoint.values, w)).max(axis=0)
        assert np.all(distance <= bound * (1 + 1e-9))
        tightness.append(np.median(distance / bound))
    assert np.median(tightness) > 0.5  # not vacuous


def test_zero_damping_lower_bound_gives_infinite_bound_at_resonance():
    model = IntervalModel([[0.0, 0.9, 0.0, 3.0]], [[0.1, 1.1, 0.0, 5.0]])
    bound = mode_mismatch_bounds(model, [1.0, 5.0])[0]
    assert np.isinf(bound[0]) and np.isfinite(bound[1])
