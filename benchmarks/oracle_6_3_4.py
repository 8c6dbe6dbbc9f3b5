"""Oracle check for section 6.3.4 without unmodelled dynamics: what can any single input achieve?

Reproduces the campaign state at iteration 2 (15 initial points + the first chosen input at
1.164 rad/s, seed 1), then, for each of 36 log-spaced frequencies in 0.3-40 rad/s, really
measures there (simulated noise), re-identifies and re-analyses, and prints the resulting
mu-bar peak. Used in RESULTS-campaign.md to show that the stall of this example is a property of
the simulated noise profile, not of the input ranking.

Usage: ``.venv/bin/python benchmarks/oracle_6_3_4.py`` (about 1.5 s CPU per frequency).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from setmem_hil.model.frequency_data import FrequencyData  # noqa: E402
from setmem_hil.identification.algorithm import identify  # noqa: E402
from setmem_hil.io.procedure_file import load_procedure  # noqa: E402
from setmem_hil.robust.analysis import analyze_robust_performance  # noqa: E402
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    proc = load_procedure(ROOT / "procedures" / "beam_6_3_4_resonance_no_unmodelled.toml")
    beam = SimulatedBeamExperiment(noise_profile="resonance", seed=1, unmodelled_dynamics=False)
    ms = [beam.measure(w) for w in proc.initial_omegas_rad_s] + [beam.measure(1.164)]
    first = identify(FrequencyData.from_measurements(ms[:-1]), proc.prior)
    data = FrequencyData.from_measurements(ms)
    current = identify(data, proc.prior, previous=first.model)
    print(f"iteration 2: mu-bar {analyze_robust_performance(current.model, proc.weights).mu_peak:.3f}")
    for w in np.geomspace(0.3, 40.0, 36):
        trial = SimulatedBeamExperiment(noise_profile="resonance", seed=1, unmodelled_dynamics=False)
        trial.n_measured = len(ms)  # the noise the campaign's next measurement would get
        m = trial.measure(w)
        res = identify(data.appended(FrequencyData([m.omega_rad_s], [m.response], [m.bound])), proc.prior,
                       previous=current.model)
        print(f"{w:8.3f} rad/s -> mu-bar {analyze_robust_performance(res.model, proc.weights).mu_peak:.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
