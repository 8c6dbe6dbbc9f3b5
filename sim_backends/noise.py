"""Bounded complex measurement noise and the thesis's noise-bound profiles.

Noise is drawn uniformly in magnitude (0 to the bound) and in phase (0 to 2 pi), as in
section 6.2, from a seeded ``numpy.random.Generator``.

Profiles (the additive-noise bound as a function of frequency):

``fully_damped`` (section 6.2, figure 6-4)
    ``|G|`` of the true beam with every pole and zero moved to damping 1.
``snr10`` (section 6.3.3)
    10% of the true ``|G(j omega)|``.
``resonance`` (section 6.3.4, figure 6-28)
    Large near the first three natural frequencies, small elsewhere. The thesis shows it only
    as a figure; we take ``max(fully_damped, 1.5 |G|)`` inside +-15% of each of the first three
    natural frequencies and ``0.5 fully_damped`` elsewhere: the SNR at the resonances is below 1
    and highest near the zeros, which is the figure's qualitative shape.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import fully_damped_magnitude

NOISE_PROFILES = ("fully_damped", "snr10", "resonance", "none")


def bounded_complex_noise(bound: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Complex noise with ``|n| <= bound``: magnitude uniform in [0, bound], phase uniform."""
    bound = np.asarray(bound, dtype=float)
    magnitude = rng.uniform(0.0, 1.0, size=bound.shape) * bound
    phase = rng.uniform(0.0, 2.0 * np.pi, size=bound.shape)
    return magnitude * np.exp(1j * phase)


def noise_bound_function(profile: str, truth: ModalParameters, scale: float = 1.0) -> Callable[[np.ndarray], np.ndarray]:
    """The additive-noise bound ``R(omega)`` of a named profile, times ``scale``."""
    if profile not in NOISE_PROFILES:
        raise ValueError(f"noise profile: expected one of {NOISE_PROFILES}, found {profile!r}")

    def bound(omega_rad_s):
        w = np.asarray(omega_rad_s, dtype=float)
        if profile == "none":
            return np.zeros_like(w)
        if profile == "snr10":
            return scale * 0.1 * np.abs(truth.frequency_response(w)).reshape(w.shape)
        base = fully_damped_magnitude(truth, w)
        if profile == "fully_damped":
            return scale * base
        near = np.zeros(w.shape, dtype=bool)
        for wn in truth.natural_frequencies[:3]:
            near |= np.abs(w / wn - 1.0) < 0.15
        g = np.abs(truth.frequency_response(w)).reshape(w.shape)
        return scale * np.where(near, np.maximum(base, 1.5 * g), 0.5 * base)

    return bound
