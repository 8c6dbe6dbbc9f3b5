"""Issue 18: the 6.3.2 campaign at any frequency scale (figure-6-12 tables side by side).

Runs the thesis section 6.3.2 campaign on the simulated beam at S = 1 (first mode 1 rad/s) and at
the scales given (default 314.159, i.e. 50 Hz), with the weights time-scaled, and prints k,
mu-bar and the next frequency divided by S for each, plus the largest relative mu-bar
difference. Usage: python benchmarks/scale_invariance.py [S ...]
"""

from __future__ import annotations

import sys
import time

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure import default_procedure


def campaign(S: float):
    procedure = default_procedure() if S == 1.0 else default_procedure().time_scaled(S)
    t0 = time.perf_counter()
    with open_experiment(procedure, procedure.seed) as experiment:
        summary = run_campaign(procedure, experiment)
    return summary, time.perf_counter() - t0


def main(argv: list[str]) -> int:
    scales = [float(a) for a in argv] or [314.159]
    ref, t_ref = campaign(1.0)
    print(f"S = 1: reached={ref.reached_goal}, {ref.experiments_added} added, {t_ref:.1f} s")
    for S in scales:
        run, t = campaign(S)
        print(f"\nS = {S:g} (first mode {S / 6.283185307:.3f} Hz): reached={run.reached_goal}, "
              f"{run.experiments_added} added, {t:.1f} s")
        print(f"{'k':>3} {'mu-bar (S=1)':>13} {'mu-bar (S)':>13} {'next/S (S=1)':>14} {'next/S (S)':>14}")
        worst = 0.0
        for a, b in zip(ref.iterations, run.iterations):
            na = "-" if a.next_omega is None else f"{a.next_omega:.6f}"
            nb = "-" if b.next_omega is None else f"{b.next_omega / S:.6f}"
            worst = max(worst, abs(b.mu_peak - a.mu_peak) / a.mu_peak)
            print(f"{a.k:>3} {a.mu_peak:>13.6f} {b.mu_peak:>13.6f} {na:>14} {nb:>14}")
        same = [it.next_omega for it in ref.iterations] == [None if it.next_omega is None else it.next_omega / S for it in run.iterations]
        print(f"largest relative mu-bar difference {worst:.2e}; same experiments x S: "
              f"{len(ref.iterations) == len(run.iterations) and (same or 'within rounding')}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
