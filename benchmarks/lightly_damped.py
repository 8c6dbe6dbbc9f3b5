"""Lightly damped structures through the emulated instruments (issue 24): what waiting them out costs.

For damping 0.01 (the thesis beam), 0.002 and 0.0005 this runs full campaigns (Algorithm 5.1)
through the real-instrument drivers against the emulated 33500B + SR830 + SR860 (exact modal
transients behind the lock-ins' filters, a virtual clock), and prints:

* the decay times ``1 / (zeta w_i)`` of the three modelled modes;
* the rig time per dwell (median) and its wait for ringing modes (median; ``DECAY_TIMES`` decay
  times of every mode whose beat passes the lock-in filter, from the current pole intervals);
* the largest error / bound of any point, the bound *without* the ``|W1|`` allowance for the
  unmodelled modes (must stay <= 1);
* the final interval widths of ``a1`` and ``a0`` per mode relative to the same campaign at
  damping 0.01 (median over seeds);
* whether mu-bar < 1 was reached and with how many added experiments.

    python benchmarks/lightly_damped.py [--seeds 1-3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def seeds_arg(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def campaign(damping: float, seed: int, out: Path) -> dict:
    from setmem_hil.campaign.session import start_run
    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.journal import read_snapshot
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.loopback.instrument_emulation import with_damping
    from rich.console import Console

    procedure = with_damping(load_procedure(REPO / "procedures" / "instruments_emulated.toml"), damping)
    opened, waits = [], []

    def opener(p, s):
        exp = open_experiment(p, s)
        measure = exp.measure

        def measured(w):
            m = measure(w)
            waits.append(exp.last_ringdown.get("waited_s", 0.0))
            return m

        exp.measure = measured
        opened.append(exp)
        return exp

    outcome = start_run(procedure, out / f"d{damping}-s{seed}", seed=seed, opener=opener, console=Console(quiet=True),
                        quiet_report_hint=True)
    exp = opened[0]
    snap = read_snapshot(out / f"d{damping}-s{seed}")
    w1 = exp.extra_bound
    ratios = [abs(m.response - exp.bench.true_response(m.omega_rad_s)) / (m.bound - w1(m.omega_rad_s)) for m in snap.measurements]
    last = snap.iterations[-1]
    return {"rig_per_dwell": [m.rig_s for m in snap.measurements], "waits": waits, "worst": max(ratios),
            "width": (last.upper - last.lower)[:, :2], "reached": outcome.summary["reached_goal"],
            "added": outcome.summary["experiments_added"], "rig_s": outcome.summary.get("rig_s", 0.0)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=seeds_arg, default=seeds_arg("1-3"), help="seeds A-B (default 1-3)")
    args = parser.parse_args(argv)
    from setmem_hil.sim_backends.beam import beam_natural_frequencies

    wn = beam_natural_frequencies(3)
    results = {}
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for damping in (0.01, 0.002, 0.0005):
            results[damping] = [campaign(damping, seed, Path(tmp)) for seed in args.seeds]
    reference = np.median([r["width"] for r in results[0.01]], axis=0)
    print(f"seeds {args.seeds[0]}-{args.seeds[-1]}; {time.perf_counter() - start:.0f} s wall\n")
    print("| damping | decay times 1/(zeta w), modes 1-3 (s) | rig s per dwell (median) | wait s per dwell (median) | "
          "wait s per dwell (max) | rig s per campaign (median) | worst error/bound (no W1) | a1 width / at 0.01, modes 1-3 | a0 width / at 0.01, modes 1-3 | reached | added (median) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for damping, runs in results.items():
        decay = ", ".join(f"{1 / (damping * w):.0f}" for w in wn)
        rig = statistics.median(x for r in runs for x in r["rig_per_dwell"])
        wait = statistics.median(x for r in runs for x in r["waits"])
        worst = max(r["worst"] for r in runs)
        width = np.median([r["width"] for r in runs], axis=0) / reference
        wait_max = max(x for r in runs for x in r["waits"])
        campaign_rig = statistics.median(sum(r["rig_per_dwell"]) for r in runs)
        print(f"| {damping:g} | {decay} | {rig:.0f} | {wait:.0f} | {wait_max:.0f} | {campaign_rig:.0f} | {worst:.3f} | "
              f"{', '.join(f'{x:.2f}' for x in width[:, 0])} | {', '.join(f'{x:.2f}' for x in width[:, 1])} | "
              f"{sum(r['reached'] for r in runs)}/{len(runs)} | {statistics.median(r['added'] for r in runs):g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
