"""Experiments needed to reach mu-bar < 1 on the simulated beam (thesis section 6.3.2).

For each strategy (the thesis's mu-based input design and the three baselines of
:mod:`setmem_hil.design.strategies`) and each seed, runs the section 6.3.2 campaign (15 initial points,
fully damped noise bound plus W1, b1 = 0) until mu-bar < 1 or the cap, and prints the number
of added experiments (">cap" when the goal was not reached), the median over seeds, and the
compute time per iteration (identification + H2 design + mu analysis with the safeguard +
input choice; the simulated dwell itself takes no time).

Usage::

    .venv/bin/python benchmarks/experiments_to_goal.py [--seeds 10] [--cap 30] [--workers 2]
        [--strategies mu,log-sweep,random,max-reduction] [--json OUT.json] [--table-seed 1]

Runs are independent processes (``--workers``); BLAS threads are pinned to 1 per process.
Expect several minutes on 2 cores: the baselines that miss the goal run all ``cap`` iterations.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor, as_completed  # noqa: E402

STRATEGIES = ("mu", "log-sweep", "random", "max-reduction")


def run_one(strategy: str, seed: int, cap: int) -> dict:
    """One campaign; returns its summary document plus timing statistics."""
    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.io.procedure import Goal, default_procedure
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    proc = default_procedure()
    proc = dataclasses.replace(proc, seed=seed, goal=Goal(mu_target=1.0, max_experiments=cap))
    sim = proc.backend.simulation
    exp = SimulatedBeamExperiment(noise_profile=sim.noise_profile, seed=seed,
                                  unmodelled_dynamics=sim.unmodelled_dynamics, noise_scale=sim.noise_scale)
    t0 = time.perf_counter()
    summary = run_campaign(proc, exp, seed=seed, strategy=strategy)
    doc = summary.to_document()
    doc["total_s"] = time.perf_counter() - t0
    return doc


def fmt_needed(doc: dict, cap: int) -> str:
    return str(doc["experiments_added"]) if doc["reached_goal"] else f">{cap}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds 1..N (default 10)")
    ap.add_argument("--cap", type=int, default=30, help="experiment budget per campaign (default 30)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--strategies", default=",".join(STRATEGIES))
    ap.add_argument("--json", default="", help="write all summaries to this file")
    ap.add_argument("--table-seed", type=int, default=1, help="print the figure-6-12 table of the mu run of this seed")
    args = ap.parse_args(argv)
    strategies = [s.strip() for s in args.strategies.split(",") if s.strip()]
    seeds = list(range(1, args.seeds + 1))
    jobs = [(s, seed) for s in strategies for seed in seeds]
    results: dict[tuple[str, int], dict] = {}
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = {pool.submit(run_one, s, seed, args.cap): (s, seed) for s, seed in jobs}
        for fut in as_completed(futures):
            key = futures[fut]
            results[key] = fut.result()
            d = results[key]
            print(f"  done {key[0]:>13s} seed {key[1]:2d}: {fmt_needed(d, args.cap):>4s} experiments, "
                  f"final mu {d['final_mu_peak']:.3f}, {d['compute_s_per_iteration']:.2f} s/iteration wall, "
                  f"{d['compute_cpu_s_per_iteration']:.2f} s cpu", flush=True)
    elapsed = time.perf_counter() - t0

    print()
    print(f"Experiments added to reach mu-bar < 1 (section 6.3.2 campaign, cap {args.cap}, seeds {seeds[0]}..{seeds[-1]})")
    header = (f"{'strategy':>13s} | " + " ".join(f"{s:>4d}" for s in seeds)
              + " | median | reached | wall s/iter mean max | cpu s/iter mean max")
    print(header)
    print("-" * len(header))
    for s in strategies:
        docs = [results[(s, seed)] for seed in seeds]
        needed = [d["experiments_added"] if d["reached_goal"] else args.cap + 1 for d in docs]
        med = statistics.median(needed)
        med_s = f"{med:g}" if med <= args.cap else f">{args.cap}"
        per_iter = [it["compute_s"] for d in docs for it in d["iterations"]]
        per_iter_cpu = [it["compute_cpu_s"] for d in docs for it in d["iterations"]]
        print(f"{s:>13s} | " + " ".join(f"{fmt_needed(d, args.cap):>4s}" for d in docs)
              + f" | {med_s:>6s} | {sum(d['reached_goal'] for d in docs):>3d}/{len(docs):<3d} | "
              f"{statistics.mean(per_iter):14.2f} {max(per_iter):5.2f} | {statistics.mean(per_iter_cpu):13.2f} {max(per_iter_cpu):5.2f}")
    print(f"(wall time {elapsed:.0f} s with {args.workers} worker processes)")

    if "mu" in strategies and (("mu", args.table_seed) in results):
        d = results[("mu", args.table_seed)]
        print()
        print(f"mu strategy, seed {args.table_seed} (figure 6-12 style)")
        print(f"{'k':>3s} {'points':>6s} {'mu-bar':>8s} {'at rad/s':>9s} {'next rad/s':>10s} {'safeguard':>20s} {'wall s':>7s} {'cpu s':>6s}")
        for it in d["iterations"]:
            nxt = "-" if it["next_omega"] is None else f"{it['next_omega']:.3f}"
            print(f"{it['k']:>3d} {it['n_points']:>6d} {it['mu_peak']:8.4f} {it['mu_peak_omega']:9.3f} {nxt:>10s} "
                  f"{it['safeguard']:>20s} {it['compute_s']:7.2f} {it['compute_cpu_s']:6.2f}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({f"{s}/{seed}": d for (s, seed), d in results.items()}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
