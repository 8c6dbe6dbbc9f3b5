"""A compensator's continuous frequency response at many frequencies (stop 66): the implemented
loop's lag envelope asks for up to 51,200 per analysis.

Prints, measured in this run, the time of :func:`setmem_hil.robust.controller_forms.frequency_response`
(one complex Schur form, every frequency by back-substitution) and of python-control's own
evaluation (one slycot call per frequency) on a 15-state compensator, their ratio, and the
largest relative difference between the two.

    .venv/bin/python benchmarks/compensator_response.py
"""

from __future__ import annotations

import time

import control
import numpy as np

from setmem_hil.robust.controller_forms import frequency_response


def best_of(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    np.random.seed(3)
    K = control.rss(15, 1, 1)
    w = np.geomspace(1e-2, 1e4, 51_200)
    ours = best_of(lambda: frequency_response(K, w))
    theirs = best_of(lambda: control.frequency_response(K, w))
    a = frequency_response(K, w)
    b = np.asarray(control.frequency_response(K, w).complex, dtype=complex).reshape(-1)
    print(f"51,200 frequencies, 15 states: Schur back-substitution {ours * 1e3:.1f} ms, python-control {theirs * 1e3:.1f} ms, "
          f"ratio {theirs / ours:.1f}x; largest relative difference {np.max(np.abs(a - b) / np.abs(b)):.1e}")


if __name__ == "__main__":
    main()
