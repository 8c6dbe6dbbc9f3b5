"""Test doubles for the run/resume/kill tests (not collected: no ``test_`` prefix).

``fast_analysis`` replaces the robust analysis (H2 design + mixed mu, seconds per iteration)
with a cheap deterministic function of the interval model, so that campaigns can be interrupted
and resumed many times within the test budget. It keeps what the replay depends on: a mu-bar
that shrinks with the intervals and mu-sensitivities that single out the widest parameters, so
the input design still chooses different frequencies at different iterations. One test in
``test_resume.py`` runs the real analysis.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from setmem_hil.errors import DeviceError

CHEAP_PROCEDURE = """
name = "cheap"
description = "Three beam modes, cheap identification and input design settings for tests."
seed = 3

[[mode]]
omega_min = 0.884
omega_max = 1.125
zeta_max = 0.5
b1 = 0.0

[[mode]]
omega_min = 5.41
omega_max = 7.34
zeta_max = 0.5
b1 = 0.0

[[mode]]
omega_min = 16.35
omega_max = 19.81
zeta_max = 0.5
b1 = 0.0

[identification]
gamma = 2.0
max_partitions = 3

[initial]
omega_rad_s = [0.8, 0.9, 0.95, 1.06, 1.15, 5.0136, 5.6403, 5.9536, 6.643, 7.207, 14.0376, 15.7923, 16.6697, 18.5998, 20.1791]

[goal]
mu_target = 0.5
max_experiments = {max_experiments}

[input_design]
candidates_base = 40
candidates_per_iteration = 3
exact_resolve_top = 1
"""


def cheap_procedure_text(max_experiments: int = 3) -> str:
    return CHEAP_PROCEDURE.replace("{max_experiments}", str(int(max_experiments)))


def fast_analysis(model, weights=None, omega_rad_s=None, controller=None, gain=None, design="h2", warm_start=None,
                  tuning=None, certificate_rtol=None):
    """Deterministic stand-in for ``analyze_robust_performance`` (same attributes; the design
    method and its warm start change nothing here but the ``design`` it reports, as the real one
    does: a compensator it designs is the method's, a given one is "given")."""
    rel = np.where(model.fixed, 0.0, model.width / np.maximum(np.abs(model.upper) + np.abs(model.lower), 1e-12))
    mu_peak = 0.5 + float(rel.sum())
    w = np.geomspace(0.1, 100.0, 50)
    sens = {
        f"{p}_{i + 1}": float(rel[i, j])
        for i in range(model.n_modes) for j, p in enumerate(("a1", "a0", "b1", "b0")) if not model.fixed[i, j]
    }
    return SimpleNamespace(
        mu_peak=mu_peak, mu_peak_omega=4.4, mu_lower_peak=0.9 * mu_peak, omega=w,
        mu=mu_peak * np.exp(-np.log(w / 4.4) ** 2), mu_lower=0.9 * mu_peak * np.exp(-np.log(w / 4.4) ** 2),
        sensitivities=sens, controller="C", controller_order=6, design=design if controller is None else "given",
    )


def install_fast_analysis(monkeypatch=None) -> None:
    """Patch ``setmem_hil.robust.analysis.analyze_robust_performance`` (run_campaign imports it per call)."""
    import setmem_hil.robust.analysis as ra

    if monkeypatch is not None:
        monkeypatch.setattr(ra, "analyze_robust_performance", fast_analysis)
    else:
        ra.analyze_robust_performance = fast_analysis


class ForwardingExperiment:
    """Base of the test doubles that wrap an experiment: ``n_measured`` is the inner one's (the
    campaign sets it when it resumes)."""

    def __init__(self, inner):
        self.inner = inner

    @property
    def n_measured(self):
        return self.inner.n_measured

    @n_measured.setter
    def n_measured(self, value):
        self.inner.n_measured = value


class InterruptingExperiment(ForwardingExperiment):
    """Wraps an experiment; raises KeyboardInterrupt (or DeviceError) on its ``interrupt_at``-th dwell.

    Records whether ``close()`` (exciter to zero) was called; ``delay_s`` makes each dwell take time.
    """

    def __init__(self, inner, interrupt_at: int | None, error: type[BaseException] = KeyboardInterrupt, delay_s: float = 0.0):
        super().__init__(inner)
        self.delay_s = delay_s
        self.interrupt_at = interrupt_at
        self.error = error
        self.calls = 0
        self.closed = False

    def total_bound(self, omega_rad_s):
        return self.inner.total_bound(omega_rad_s)

    def measure(self, omega_rad_s):
        self.calls += 1
        if self.interrupt_at is not None and self.calls == self.interrupt_at:
            if self.error is DeviceError:
                raise DeviceError(f"fake rig stopped answering at {omega_rad_s:g} rad/s")
            raise self.error()
        if self.delay_s:
            import time

            time.sleep(self.delay_s)  # a dwell takes time: lets a test kill the process mid-campaign
        return self.inner.measure(omega_rad_s)

    def take_raw_records(self):
        """The inner experiment's raw records (its points pass through unchanged)."""
        return self.inner.take_raw_records()

    def close(self):
        self.closed = True
        self.inner.close()


def simulated(procedure, seed: int):
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    sim = procedure.backend.simulation
    return SimulatedBeamExperiment(noise_profile=sim.noise_profile, seed=seed, unmodelled_dynamics=sim.unmodelled_dynamics, noise_scale=sim.noise_scale)
