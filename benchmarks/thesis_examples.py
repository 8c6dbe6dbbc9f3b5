"""Thesis sections 6.3.2, 6.3.3 and both runs of 6.3.4 on the simulated beam, as figure-6-12 tables.

Runs the shipped procedures (``procedures/beam_6_3_*.toml``) with the mu-based input design and
prints, per example, mu-bar and the chosen frequency per iteration, and whether the thesis's
qualitative outcome holds:

* 6.3.2 (fully damped bound + W1): reaches mu-bar < 1 (the thesis needed 12 added points);
* 6.3.3 (10% of |G| + W1): starts lower than 6.3.2, chooses inputs near the natural
  frequencies, reaches mu-bar < 1 (more slowly than 6.3.2 in the thesis);
* 6.3.4 with unmodelled dynamics (large noise at the resonances + W1): stalls above 1;
* 6.3.4 without unmodelled dynamics: converges (mu-bar drops below 1 after a few inputs).

Usage::

    .venv/bin/python benchmarks/thesis_examples.py [--seed 1] [--only 6.3.4a,6.3.4b] [--cap N] [--json OUT]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = {
    "6.3.2": ("beam_6_3_2.toml", "reaches mu-bar < 1"),
    "6.3.3": ("beam_6_3_3_snr10.toml", "reaches mu-bar < 1; inputs near the natural frequencies"),
    "6.3.4a": ("beam_6_3_4_resonance.toml", "stalls: mu-bar stays above 1 (unmodelled dynamics + mismatch dominate)"),
    "6.3.4b": ("beam_6_3_4_resonance_no_unmodelled.toml", "converges: mu-bar < 1 after a few inputs"),
}


def run_example(name: str, seed: int, cap: int | None) -> dict:
    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    proc = load_procedure(ROOT / "procedures" / EXAMPLES[name][0])
    if cap is not None:
        proc = dataclasses.replace(proc, goal=dataclasses.replace(proc.goal, max_experiments=cap))
    sim = proc.backend.simulation
    exp = SimulatedBeamExperiment(noise_profile=sim.noise_profile, seed=seed, unmodelled_dynamics=sim.unmodelled_dynamics,
                                  n_modelled=proc.prior.n_modes, noise_scale=sim.noise_scale)

    def show(event, **info):
        if event == "iteration":
            print(f"    k={info['k']:2d} points={info['n_points']:2d} mu-bar={info['mu_peak']:.4f} "
                  f"(at {info['mu_peak_omega']:.3f} rad/s, {info['safeguard']})", flush=True)
        elif event == "chosen":
            print(f"          next {info['next_omega']:.3f} rad/s", flush=True)

    print(f"== {name}: {EXAMPLES[name][0]}, seed {seed}, budget {proc.goal.max_experiments}", flush=True)
    summary = run_campaign(proc, exp, seed=seed, progress=show)
    doc = summary.to_document()
    doc["example"] = name
    doc["procedure"] = EXAMPLES[name][0]
    return doc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", default=",".join(EXAMPLES))
    ap.add_argument("--cap", type=int, default=None, help="override the procedures' experiment budget")
    ap.add_argument("--json", default="")
    args = ap.parse_args(argv)
    docs = {}
    for name in [s.strip() for s in args.only.split(",") if s.strip()]:
        docs[name] = run_example(name, args.seed, args.cap)
    print()
    for name, d in docs.items():
        print(f"{name} ({d['procedure']}), thesis: {EXAMPLES[name][1]}")
        print(f"  {'k':>3s} {'points':>6s} {'mu-bar':>8s} {'next rad/s':>10s}")
        for it in d["iterations"]:
            nxt = "-" if it["next_omega"] is None else f"{it['next_omega']:.3f}"
            print(f"  {it['k']:>3d} {it['n_points']:>6d} {it['mu_peak']:8.4f} {nxt:>10s}")
        print(f"  -> {'reached' if d['reached_goal'] else 'did not reach'} mu-bar < 1 with {d['experiments_added']} added "
              f"experiments; final mu-bar {d['final_mu_peak']:.4f}; {d['compute_cpu_s_per_iteration']:.2f} s cpu/iteration")
    if args.json:
        Path(args.json).write_text(json.dumps(docs, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
