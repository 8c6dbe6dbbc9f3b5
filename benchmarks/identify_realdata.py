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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--b0", type=float, default=None)
    ap.add_argument("--tight", action="store_true")
    args = ap.parse_args(argv)
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
