"""Benchmark: mu-bar certified between grid points (issue 27, item 3), its cost and what it finds.

Prints, in one run:

* the 6.3.2 campaign (default procedure, simulated beam): every analysis timed, and inside it the
  band certificate (:func:`setmem_hil.robust.mu_certificate.certify_band`); the ratio
  ``analysis time / analysis time without the certificate`` (goal: <= 2), the intervals and
  Hamiltonian tests per analysis, and whether every analysis was certified;
* the thesis's Table B-1 model: the certified level against 3000 precise solves on a dense grid;
* a lightly damped mode built between two grid points: the 200-point grid's peak, the certified
  peak and a dense sweep across the resonance.

Run: ``.venv/bin/python benchmarks/mu_certificate.py``.
"""

from __future__ import annotations

import os
import time

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")

import setmem_hil.robust.analysis as analysis_module  # noqa: E402
from setmem_hil.campaign.runner import run_campaign  # noqa: E402
from setmem_hil.experiment_factory import open_experiment  # noqa: E402
from setmem_hil.io.procedure import default_procedure  # noqa: E402
from setmem_hil.model.modal_model import IntervalModel  # noqa: E402
from setmem_hil.model.weights import THESIS_WEIGHTS  # noqa: E402
from setmem_hil.robust.augmented_plant import augmented_plant  # noqa: E402
from setmem_hil.robust.h2_design import h2_controller_for_plant  # noqa: E402
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper  # noqa: E402
from setmem_hil.robust.uncertain_plant import uncertain_plant  # noqa: E402
from setmem_hil.sim_backends.beam import beam_parameters  # noqa: E402

TABLE_B1_LOWER = [[2.0911e-9, 8.8827e-1, 0.0, 2.7028], [4.5511e-9, 3.3851e1, 0.0, -1.4572], [1.6299e-9, 2.6725e2, 0.0, -7.8492]]
TABLE_B1_UPPER = [[1.2140e-1, 1.2333, 0.0, 7.6251], [5.3030e-1, 4.3162e1, 0.0, 7.6061], [2.5572, 3.5747e2, 0.0, 1.5549e1]]


def campaign_cost() -> None:
    analysis_s, certificate_s, certs, results = [], [], [], []
    certify, analyze = analysis_module.certify_grid, analysis_module.analyze_robust_performance

    def timed_certify(*args):
        t = time.perf_counter()
        out = certify(*args)
        certificate_s.append(time.perf_counter() - t)
        certs.append(out)
        return out

    def timed_analyze(*args, **kwargs):
        t = time.perf_counter()
        out = analyze(*args, **kwargs)
        analysis_s.append(time.perf_counter() - t)
        results.append(out)
        return out

    analysis_module.certify_grid, analysis_module.analyze_robust_performance = timed_certify, timed_analyze
    try:
        procedure = default_procedure()
        with open_experiment(procedure, procedure.seed) as experiment:
            summary = run_campaign(procedure, experiment)
    finally:
        analysis_module.certify_grid, analysis_module.analyze_robust_performance = certify, analyze
    total, cert = sum(analysis_s), sum(certificate_s)
    print(f"6.3.2 campaign (seed {procedure.seed}): {summary.experiments_added} added, final mu-bar {summary.final_mu_peak:.4f}, "
          f"reached goal {summary.reached_goal}")
    print(f"  {len(analysis_s)} analyses: {total:.2f} s in all, of which the certificate {cert:.2f} s; "
          f"ratio to the analysis without it {total / (total - cert):.2f}x (goal <= 2x)")
    print(f"  intervals per analysis {min(c.n_intervals for c in certs)}-{max(c.n_intervals for c in certs)}, "
          f"Hamiltonian tests {min(c.n_scalings for c in certs)}-{max(c.n_scalings for c in certs)}, "
          f"points added {min(c.omega.size for c in certs)}-{max(c.omega.size for c in certs)}; "
          f"certified {sum(c.certified for c in certs)}/{len(certs)}; "
          f"largest rise of the peak over the grid's {max(r.mu_peak / r.mu_peak_grid for r in results) - 1:.1e} (relative)")


def closed_loop(model: IntervalModel, controller=None):
    plant = augmented_plant(uncertain_plant(model), THESIS_WEIGHTS)
    K = h2_controller_for_plant(plant) if controller is None else controller
    return plant.closed_loop(K), MuStructure(plant.n_real, plant.n_complex)


def table_b1_against_dense() -> None:
    model = IntervalModel(TABLE_B1_LOWER, TABLE_B1_UPPER)
    t = time.perf_counter()
    result = analysis_module.analyze_robust_performance(model)
    elapsed = time.perf_counter() - t
    system, structure = closed_loop(model, result.controller)
    dense = mixed_mu_upper(system.frequency_response(np.geomspace(0.1, 1000.0, 3000)), structure).beta.max()
    print(f"Table B-1: analysis {elapsed:.2f} s; grid peak {result.mu_peak_grid:.6f}, certified level {result.mu_certified_level:.6f} "
          f"({result.mu_certified_intervals} intervals); 3000-point dense max {dense:.6f} (<= level: {dense <= result.mu_certified_level})")


def missed_peak() -> None:
    values = np.vstack([beam_parameters().truncated(3).values, [2 * 1e-4 * 2.9, 2.9**2, 0.0, 0.05]])
    model = IntervalModel(values.copy(), values.copy())
    result = analysis_module.analyze_robust_performance(model)
    system, structure = closed_loop(model, result.controller)
    window = np.linspace(result.mu_peak_omega * 0.995, result.mu_peak_omega * 1.005, 4001)
    dense = mixed_mu_upper(system.frequency_response(window), structure).beta.max()
    print(f"lightly damped mode at 2.9 rad/s (zeta 1e-4) between grid points: grid peak {result.mu_peak_grid:.4f}, "
          f"certified peak {result.mu_peak:.5f} at {result.mu_peak_omega:.5f} rad/s (level {result.mu_certified_level:.5f}), "
          f"dense sweep (4001 points) {dense:.5f}")


def main() -> None:
    campaign_cost()
    table_b1_against_dense()
    missed_peak()


if __name__ == "__main__":
    main()
