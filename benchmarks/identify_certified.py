"""Certified one-mode bounds on random extreme problems (issue 14 item 5): figures.

Runs the problems of ``tests/test_certified_bounds.py`` (damping 1e-5..0.3, natural frequencies
1e-2..1e5 rad/s, receptance 1e-7..10) and prints how many bounds were certified or flagged, how
often the truth was inside, the median interval width relative to the prior box and the time.
Usage: ``python benchmarks/identify_certified.py [N]`` (default 1000; the 40-digit re-check of the
certificates is done by the test, not here).
"""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path

import numpy as np


def main(n_cases: int = 1000) -> None:
    path = Path(__file__).resolve().parents[1] / "tests" / "test_certified_bounds.py"
    spec = importlib.util.spec_from_file_location("cert_cases", path)
    cases = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cases)
    certified = flagged = inside = emptied = 0
    widths = []
    t0 = time.perf_counter()
    for seed in range(n_cases):
        truth, omega, g, C, lo, hi, problem, sol = cases.run_case(seed)
        free = problem.free
        if not sol.feasible:
            emptied += 1
            continue
        inside += bool(np.all(sol.lower[free] <= truth[free]) and np.all(truth[free] <= sol.upper[free]))
        certified += len(problem.last_certificates)
        flagged += len(sol.unverified)
        widths.extend((sol.upper[free] - sol.lower[free]) / (hi[free] - lo[free]))
    elapsed = time.perf_counter() - t0
    print(f"{n_cases} random one-mode problems in {elapsed:.1f} s ({elapsed / n_cases * 1e3:.1f} ms each)")
    print(f"  truth inside: {inside}/{n_cases}; boxes wrongly proved empty: {emptied}")
    print(f"  bounds certified: {certified}, flagged unverified: {flagged}")
    print(f"  median width / prior width: {np.median(widths):.3g}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000)
