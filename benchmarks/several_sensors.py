"""Benchmark: the 6.3.2 campaign with three sensors against one (issue 25).

The simulated cantilever with the force at the tip; one sensor at the tip (the thesis), or
three at 1.0, 0.4 and 0.7 of the length with the tip as the control output. The tip's data are
the same in both runs of a seed (each sensor has its own noise stream), so the difference is
what the other two sensors add. Prints, per seed 1-10 and as medians: experiments added to
reach mu-bar < 1, rig time, the final mu-bar, and whether every output's true parameters lie
inside every interval of every iteration (read back from the journal).

Run: ``.venv/bin/python benchmarks/several_sensors.py [--seeds A-B]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from setmem_hil.campaign.runner import run_campaign  # noqa: E402
from setmem_hil.experiment_factory import open_experiment  # noqa: E402
from setmem_hil.io.journal import Journal  # noqa: E402
from setmem_hil.io.procedure import default_procedure  # noqa: E402
from setmem_hil.io.procedure_file import format_procedure  # noqa: E402

SENSOR_SETS = {"1 sensor": (1.0,), "3 sensors": (1.0, 0.4, 0.7)}


def one_run(args: tuple[str, int]) -> dict:
    label, seed = args
    base = default_procedure()
    sim = dataclasses.replace(base.backend.simulation, sensors=SENSOR_SETS[label])
    procedure = dataclasses.replace(base, seed=seed, backend=dataclasses.replace(base.backend, simulation=sim))
    with tempfile.TemporaryDirectory() as tmp:
        journal = Journal.create(Path(tmp) / "journal.sqlite", procedure_text=format_procedure(procedure), procedure_name="bench",
                                 seed=seed, software_version="bench", backend="sim", strategy="mu")
        with open_experiment(procedure, seed) as experiment:
            summary = run_campaign(procedure, experiment, journal, seed=seed)
            truths = [t.truncated(procedure.prior.n_modes) for t in experiment.truths]
            c = sim.control_output - 1
            ordered = [truths[c]] + [t for i, t in enumerate(truths) if i != c]
        inside = True
        for record in journal.iterations():
            if record.outputs is None:
                inside &= bool(np.all((record.lower <= ordered[0].values) & (ordered[0].values <= record.upper)))
            else:
                for lo, hi, truth in zip(record.outputs["lower"], record.outputs["upper"], ordered):
                    inside &= bool(np.all((np.array(lo) <= truth.values) & (truth.values <= np.array(hi))))
        journal.close()
    return {"label": label, "seed": seed, "added": summary.experiments_added, "rig_s": summary.rig_s,
            "mu": summary.final_mu_peak, "goal": summary.reached_goal, "inside": inside}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="1-10", help="A-B (inclusive)")
    a, b = (int(x) for x in parser.parse_args().seeds.split("-"))
    jobs = [(label, seed) for seed in range(a, b + 1) for label in SENSOR_SETS]
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        results = list(pool.map(one_run, jobs))
    for seed in range(a, b + 1):
        row = {r["label"]: r for r in results if r["seed"] == seed}
        print(f"seed {seed:3d}: " + "; ".join(f"{label}: {r['added']} added, {r['rig_s']:.0f} rig s, mu-bar {r['mu']:.4f}"
                                             f"{'' if r['goal'] else ' (budget)'}{'' if r['inside'] else ' TRUTH OUTSIDE'}"
                                             for label, r in row.items()))
    for label in SENSOR_SETS:
        rs = [r for r in results if r["label"] == label]
        print(f"{label}: median {statistics.median(r['added'] for r in rs)} added (mean {statistics.mean(r['added'] for r in rs):.1f}), "
              f"median rig {statistics.median(r['rig_s'] for r in rs):.0f} s (mean {statistics.mean(r['rig_s'] for r in rs):.0f} s), "
              f"goal {sum(r['goal'] for r in rs)}/{len(rs)}, truth inside every interval {sum(r['inside'] for r in rs)}/{len(rs)}")


if __name__ == "__main__":
    main()
