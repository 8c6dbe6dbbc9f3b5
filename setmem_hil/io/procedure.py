"""Procedure files: what a technician runs (schema as dataclasses; defaults = thesis 6.3.2).

A procedure gathers everything a campaign needs: the backend and its transport settings, the
safety limits, the prior (``[[mode]]`` tables, same keys as PRIOR.toml), the noise model of the
simulated backend, the initial frequencies, the goal and experiment budget, input-design
settings, and the control weights W1, W2. Every key is documented in README.

Loading and validation (messages naming file, table and key) live in
:mod:`setmem_hil.io.procedure_file`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping


from setmem_hil.model.prior import ModePrior, Prior
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

BACKENDS = ("sim", "serial-loopback", "can-virtual", "modbus-loopback")
STRATEGIES = ("mu", "log-sweep", "random", "max-reduction")
NOISE_PROFILES = ("fully_damped", "snr10", "resonance", "none")


@dataclass(frozen=True)
class SafetyLimits:
    """Enforced in the driver layer before any command is sent."""

    max_amplitude_n: float = 1.0
    omega_min_rad_s: float = 0.05
    omega_max_rad_s: float = 2000.0
    max_dwell_s: float = 3600.0


@dataclass(frozen=True)
class SimulationSettings:
    """Simulated structure behind every backend (the fake devices simulate it too)."""

    noise_profile: str = "fully_damped"
    noise_scale: float = 1.0
    unmodelled_dynamics: bool = True


@dataclass(frozen=True)
class BackendSettings:
    kind: str = "sim"
    simulation: SimulationSettings = SimulationSettings()
    transport: Mapping[str, Any] = field(default_factory=dict)  # per-transport options (url, channel, ...)
    faults: Mapping[str, Any] = field(default_factory=dict)  # fault injection of fake devices


@dataclass(frozen=True)
class Goal:
    mu_target: float = 1.0
    max_experiments: int = 30


@dataclass(frozen=True)
class InputDesignSettings:
    strategy: str = "mu"
    candidates_base: int = 500  # 500 + 25 k candidates at iteration k (section 6.3.2)
    candidates_per_iteration: int = 25
    candidate_omega_min_rad_s: float = 0.1
    candidate_omega_max_rad_s: float = 1000.0
    exact_resolve_top: int = 5  # candidates re-identified exactly before choosing


@dataclass(frozen=True)
class Procedure:
    name: str
    prior: Prior
    initial_omegas_rad_s: tuple[float, ...]
    seed: int = 1
    backend: BackendSettings = BackendSettings()
    safety: SafetyLimits = SafetyLimits()
    goal: Goal = Goal()
    input_design: InputDesignSettings = InputDesignSettings()
    weights: Weights = THESIS_WEIGHTS
    discrepancy_check: bool = False
    description: str = ""
    source_text: str = ""  # the file's text, stored in the journal with the run
    source_path: str = ""


def thesis_beam_prior(b1_fixed: bool = True, b1_limit: float = 1.0) -> Prior:
    """Section 6.1 prior: omega_n bounds of the first three modes, zeta <= 0.5; b1 = 0 (6.2.2).

    With ``b1_fixed=False`` (section 6.2.1) ``b1`` is bounded by ``+-b1_limit``: a guaranteed
    start needs some bound on it (the thesis started from an "engineering judgment" constant,
    section 3.2.1); 1.0 is seven times wider than the thesis's final b1 intervals (Table 6-2).
    """
    bounds = ((0.884, 1.125), (5.41, 7.34), (16.35, 19.81))
    extra = {"b1_min": 0.0, "b1_max": 0.0} if b1_fixed else {"b1_min": -b1_limit, "b1_max": b1_limit}
    return Prior(tuple(ModePrior(lo, hi, 0.5, **extra) for lo, hi in bounds))


def thesis_6_3_2_initial_omegas() -> tuple[float, ...]:
    """15 initial points, 5 around each of the first three modes but not at the peaks.

    The thesis (figure 6-8) shows them only as a plot. We place them at ratios
    0.80, 0.90, 0.95, 1.06, 1.15 of the prior's mid natural frequency of each mode, i.e. well
    outside each half-power band (+-1%), covering the band of a priori frequency uncertainty.
    """
    ratios = (0.80, 0.90, 0.95, 1.06, 1.15)
    centres = (1.0, 6.267, 17.547)  # the true natural frequencies the prior bands surround
    return tuple(float(round(c * r, 4)) for c in centres for r in ratios)


def default_procedure() -> Procedure:
    """The section 6.3.2 campaign on the simulated beam (used by ``setmem-hil demo``)."""
    return Procedure(
        name="beam-6.3.2",
        description="Thesis section 6.3.2: simulated cantilever, fully damped noise bound plus W1, b1 = 0.",
        prior=thesis_beam_prior(),
        initial_omegas_rad_s=thesis_6_3_2_initial_omegas(),
    )
