"""Benchmark: the section 6.2.2 identification (15 points, b1 = 0, gamma <= 1.1) on the beam.

Prints wall time and the number of conic solves per run over several noise seeds, and the
largest embedding gamma where partitioning ran. Goal (issue 2): under 0.5 s on 2 cores.
Run: .venv/bin/python benchmarks/identify_beam.py
"""

from __future__ import annotations

import time

import numpy as np

from setmem_hil.identification.algorithm import identify
from setmem_hil.io.procedure import thesis_beam_prior
from setmem_hil.sim_backends.thesis_cases import section_6_2_data


def main(seeds: int = 10) -> None:
    prior = thesis_beam_prior()
    identify(section_6_2_data(0)[0], prior)  # warm-up: imports, BLAS
    times, solves, gammas, inside = [], [], [], []
    for seed in range(seeds):
        data, beam = section_6_2_data(seed)
        t0 = time.perf_counter()
        result = identify(data, prior)
        times.append(time.perf_counter() - t0)
        solves.append(result.n_solves)
        gammas.append(max((g for g, p in zip(result.embedding_gamma, result.partitioned) if p), default=float("nan")))
        inside.append(bool(result.model.contains(beam.modelled_truth).all()))
    print("section 6.2.2 identification, 15 points, b1 = 0, gamma target 1.1")
    print(f"  wall time per run: median {np.median(times) * 1e3:.1f} ms, max {np.max(times) * 1e3:.1f} ms (goal < 500 ms)")
    print(f"  conic solves per run: median {int(np.median(solves))}, max {max(solves)}")
    print(f"  time per conic solve: {np.sum(times) / np.sum(solves) * 1e6:.0f} us (including set-up)")
    print(f"  largest gamma where partitioned: {np.nanmax(gammas):.4f}")
    print(f"  truth inside every interval: {sum(inside)}/{len(inside)} seeds")


if __name__ == "__main__":
    main()
