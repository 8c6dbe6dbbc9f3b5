"""Input-selection strategies: the thesis's mu-based design and the baselines it is compared with.

``"mu"``
    Algorithm 5.1: maximise the estimated mu-bar improvement (eq. 5.3) over the candidates
    (:func:`setmem_hil.design.input_design.choose_input` with the mu-sensitivities as weights).
``"max-reduction"``
    The same effect estimates and exact re-solves, but maximising the total normalised interval
    reduction ``sum_i (1 - delta_i,new / delta_i,old)``: it ignores mu entirely.
``"log-sweep"``
    A log-frequency sweep over the candidate band that does not depend on the data. To make
    every prefix an even sweep (the campaign stops as soon as mu-bar < 1, so the order matters)
    the ``n``-th added point is at ``omega_min (omega_max / omega_min)^{v(n)}`` with ``v`` the
    base-2 van der Corput sequence (1/2, 1/4, 3/4, 1/8, ...): the first point is the
    log-centre of the band, then each pass halves the log spacing.
``"random"``
    Log-uniform in the candidate band, drawn from
    ``numpy.random.default_rng((seed, k, RANDOM_STREAM))``: reproducible for a seed, the same
    whether the campaign runs serially, resumed or on a Dask worker.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.io.procedure import STRATEGIES, InputDesignSettings

RANDOM_STREAM = 0x52414E44  # "RAND": separates this stream from the simulator's noise streams
DATA_DRIVEN = ("mu", "max-reduction")


def check_strategy(strategy: str) -> str:
    """Return ``strategy`` if known, else raise ``ValueError`` naming the allowed values."""
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy: expected one of {', '.join(STRATEGIES)}, found {strategy!r}")
    return strategy


def van_der_corput(n: int, base: int = 2) -> float:
    """``n``-th element (from 1) of the van der Corput sequence in ``base``: 1/2, 1/4, 3/4, ..."""
    if n < 1:
        raise ValueError(f"n: expected >= 1, found {n}")
    value, denom = 0.0, 1.0
    while n:
        n, digit = divmod(n, base)
        denom *= base
        value += digit / denom
    return value


def log_sweep_frequency(n_added: int, settings: InputDesignSettings = InputDesignSettings()) -> float:
    """Frequency of the ``n_added``-th added point (0-based) of the ``"log-sweep"`` baseline."""
    settings = settings.resolved()  # the thesis band when none is given (the runner resolves it)
    lo = float(settings.candidate_omega_min_rad_s)
    hi = float(settings.candidate_omega_max_rad_s)
    return float(lo * (hi / lo) ** van_der_corput(n_added + 1))


def random_frequency(seed: int | None, k: int, settings: InputDesignSettings = InputDesignSettings()) -> float:
    """Frequency of the ``"random"`` baseline at iteration ``k``: log-uniform in the band."""
    rng = np.random.default_rng((0 if seed is None else int(seed), int(k), RANDOM_STREAM))
    settings = settings.resolved()  # the thesis band when none is given (the runner resolves it)
    lo = np.log(float(settings.candidate_omega_min_rad_s))
    hi = np.log(float(settings.candidate_omega_max_rad_s))
    return float(np.exp(rng.uniform(lo, hi)))


__all__ = [
    "DATA_DRIVEN",
    "RANDOM_STREAM",
    "check_strategy",
    "log_sweep_frequency",
    "random_frequency",
    "van_der_corput",
]
