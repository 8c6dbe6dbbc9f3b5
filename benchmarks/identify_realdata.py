"""Identification time on real data (issue 14 item 4): 384 points, 6 modes, and the simulated beam.

Usage::

    python benchmarks/identify_realdata.py [--profile] [--b0 10] [--tight]

Loads ``<repo>/../shared/realdata/ladisk-pyuff-beam/frf_displacement_relaxed.csv`` and its
``prior.toml`` (skips with a message when absent). ``--b0 B`` adds ``b0_min = -B, b0_max = B`` to
every mode (the issue's hand-tightened prior; without it the residues are bootstrapped from the
data); ``--tight`` also narrows the frequency brackets to +-5% of the prior band centre and
``zeta_max`` to 0.01, as in the issue. Prints the wall time, the solve count, gamma per mode and
the verified flags; ``--profile`` adds the cProfile summary (top 15 by cumulative time). The
"before" figure is obtained by running the same script with ``PYTHONPATH`` pointing at an older
checkout (see README).
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import io
import pstats
import sys
import time
from pathlib import Path

import numpy as np

from setmem_hil.identification.algorithm import identify
from setmem_hil.io.data_file import read_data_csv
from setmem_hil.model.prior import read_prior

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "ladisk-pyuff-beam"


def load(b0: float | None, tight: bool):
    data = read_data_csv(REALDATA / "frf_displacement_relaxed.csv")
    prior = read_prior(REALDATA / "prior.toml")
    modes = []
    for m in prior.modes:
        if tight and m.omega_min > 100:
            centre = np.sqrt(m.omega_min * m.omega_max)
            m = dataclasses.replace(m, omega_min=centre / 1.05, omega_max=centre * 1.05, zeta_max=0.01)
        if b0 is not None:
            m = dataclasses.replace(m, b0_min=-b0, b0_max=b0)
        modes.append(m)
    return data, dataclasses.replace(prior, modes=tuple(modes))


def simulated(n_modes: int, n_points: int = 400):
    """The simulated beam (8-mode truth, section 6.2 noise plus |W1|), first ``n_modes`` modelled,
    ``n_points`` log-spaced points up to 1.2 x the last modelled natural frequency, priors
    +-10% in frequency, zeta_max 0.5, b1 = 0; residues bootstrapped from the data for 3 modes,
    b0 in +-10x the true residue for 6 (the bootstrap cannot contract with six +-10% bands)."""
    from setmem_hil.model.frequency_data import FrequencyData
    from setmem_hil.model.prior import ModePrior, Prior
    from setmem_hil.sim_backends.beam import BEAM_RESIDUE
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    beam = SimulatedBeamExperiment(seed=0, n_modelled=n_modes)
    wn = beam.modelled_truth.natural_frequencies
    w = np.geomspace(0.5 * wn[0], 1.2 * wn[-1], n_points)
    data = FrequencyData.from_measurements(beam.measure_many(w))
    b0 = (-10 * BEAM_RESIDUE, 10 * BEAM_RESIDUE) if n_modes > 3 else (-np.inf, np.inf)
    prior = Prior(tuple(ModePrior(0.9 * x, 1.1 * x, 0.5, 0.0, 0.0, *b0) for x in wn))
    return data, prior, beam.modelled_truth


def run_simulated() -> None:
    for n_modes in (3, 6):
        try:
            data, prior, truth = simulated(n_modes)
            t0 = time.perf_counter()
            result = identify(data, prior)
            elapsed = time.perf_counter() - t0
        except Exception as exc:
            print(f"simulated beam, {n_modes} modes: {type(exc).__name__}: {exc}")
            continue
        inside = bool(result.model.contains(truth).all())
        print(f"simulated beam, {len(data)} points x {n_modes} modes: {elapsed:.2f} s, {result.n_solves} solves, "
              f"gamma {np.array2string(result.embedding_gamma, precision=3)}, truth inside {inside}")
        for note in getattr(result, "notes", ()):
            print("  note:", note)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--b0", type=float, default=None)
    ap.add_argument("--tight", action="store_true")
    ap.add_argument("--sim", action="store_true", help="also time the simulated beam (400 points, 3 and 6 modes)")
    args = ap.parse_args(argv)
    if args.sim:
        run_simulated()
    if not REALDATA.exists():
        print(f"skipped: real data not found at {REALDATA}")
        return 0
    data, prior = load(args.b0, args.tight)
    print(f"{len(data)} points, {prior.n_modes} modes, b0 bound {args.b0}, tight prior {args.tight}")
    prof = cProfile.Profile() if args.profile else None
    t0 = time.perf_counter()
    if prof:
        prof.enable()
    try:
        result = identify(data, prior)
    except Exception as exc:  # report, do not hide: the benchmark prints what happened
        print(f"identify failed after {time.perf_counter() - t0:.2f} s: {type(exc).__name__}: {exc}")
        return 1
    finally:
        if prof:
            prof.disable()
    elapsed = time.perf_counter() - t0
    print(f"time {elapsed:.2f} s, {result.n_solves} conic solves, {result.iterations} outer iterations")
    print("gamma per mode:", np.array2string(result.embedding_gamma, precision=3))
    print("partitions:", result.partitions)
    print("verified:", getattr(result, "verified", "n/a"))
    for note in getattr(result, "notes", ()):
        print("note:", note)
    for i, (lo, hi) in enumerate(zip(result.model.lower, result.model.upper)):
        wn_lo, wn_hi = np.sqrt(lo[1]), np.sqrt(hi[1])
        print(f"mode {i + 1}: omega_n [{wn_lo:.6g}, {wn_hi:.6g}] rad/s, a1 [{lo[0]:.3g}, {hi[0]:.3g}], b0 [{lo[3]:.4g}, {hi[3]:.4g}]")
    if prof:
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("cumulative").print_stats(15)
        print(out.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
