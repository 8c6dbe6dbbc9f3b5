"""Sweep throughput and the per-strategy table (issue 9).

1. Wall time of the same N campaigns (strategy ``--timing-strategy``, seeds 1..N) run serially in
   this process and on a ``--workers``-process local Dask cluster (cluster start-up included),
   their ratio (goal: >= 1.7x with 2 workers on 2 cores), and a check that both gave identical
   campaigns (measurements and choices).
2. The per-strategy table (added experiments to reach mu-bar < 1, thesis section 6.3) over the
   seeds, from a sweep of all ``--strategies`` on the local cluster into the same directory (the
   timing campaigns are reused: the sweep skips what is done).

Usage::

    .venv/bin/python benchmarks/sweep.py [--seeds 20] [--workers 2] [--cap N] [--out DIR]
        [--procedure procedures/beam_6_3_2.toml] [--strategies mu,log-sweep,random,max-reduction]
        [--timing-strategy mu] [--skip-table]

The load average is printed before and after: other work on the machine slows the cluster
more than the serial run, so quote it with the ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _loadavg() -> str:
    try:
        return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:  # pragma: no cover
        return "load average n/a"


def _same(a: Path, b: Path, name: str) -> bool:
    """Same measurements and choices in two sweep directories for run ``name``."""
    from setmem_hil.io.journal import Journal

    with Journal.open(a / "runs" / name) as ja, Journal.open(b / "runs" / name) as jb:
        ma = [(r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in ja.measurement_rows()]
        mb = [(r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in jb.measurement_rows()]
        ca = [(i.k, i.next_omega, i.mu_peak) for i in ja.iterations()]
        cb = [(i.k, i.next_omega, i.mu_peak) for i in jb.iterations()]
    return ma == mb and ca == cb


def main(argv=None) -> int:
    from setmem_hil.io.procedure import STRATEGIES, Goal
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.sweep.runner import format_summary_table, parse_strategies, run_name, run_sweep

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--procedure", default=str(REPO / "procedures" / "beam_6_3_2.toml"))
    ap.add_argument("--seeds", type=int, default=20, help="seeds 1..N (default 20)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cap", type=int, default=None, help="override [goal] max_experiments")
    ap.add_argument("--strategies", default=",".join(STRATEGIES))
    ap.add_argument("--timing-strategy", default="mu")
    ap.add_argument("--out", default="", help="sweep directory (default: a fresh temporary one)")
    ap.add_argument("--skip-table", action="store_true", help="only the timing comparison")
    args = ap.parse_args(argv)

    proc = load_procedure(args.procedure)
    if args.cap is not None:
        proc = dataclasses.replace(proc, goal=Goal(mu_target=proc.goal.mu_target, max_experiments=args.cap))
    seeds = list(range(1, args.seeds + 1))
    strategies = parse_strategies(args.strategies)
    timing = parse_strategies(args.timing_strategy)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="sweep-bench-"))
    serial_dir, cluster_dir = out / "serial", out / "cluster"
    for d in (serial_dir, cluster_dir):
        if (d / "runs").exists() and any((d / "runs").iterdir()):
            raise SystemExit(f"{d} already holds runs; give a fresh --out")
    print(f"procedure {proc.name}, cap {proc.goal.max_experiments} added experiments, seeds 1..{args.seeds}, "
          f"{os.cpu_count()} CPUs, {_loadavg()}", flush=True)

    t0 = time.perf_counter()
    serial = run_sweep(proc, seeds, timing, serial_dir, serial=True, plot=False)
    t_serial = time.perf_counter() - t0
    print(f"serial:        {len(serial.runs)} campaigns in {t_serial:7.1f} s wall ({_loadavg()})", flush=True)
    t0 = time.perf_counter()
    cluster = run_sweep(proc, seeds, timing, cluster_dir, workers=args.workers, plot=False)
    t_cluster = time.perf_counter() - t0
    print(f"local cluster: {len(cluster.runs)} campaigns in {t_cluster:7.1f} s wall with {args.workers} worker "
          f"processes, start-up included ({_loadavg()})", flush=True)
    print(f"speed-up serial / cluster = {t_serial / t_cluster:.2f}x (goal >= 1.7x with 2 workers on 2 cores)")
    names = [run_name(s, seed) for seed in seeds for s in timing]
    same = sum(_same(serial_dir, cluster_dir, n) for n in names)
    print(f"identical campaigns (measurements, choices, mu-bar) serial vs cluster: {same}/{len(names)}")
    ser = [json.loads((serial_dir / "runs" / n / "summary.json").read_text())["wall_s"] for n in names]
    par = [json.loads((cluster_dir / "runs" / n / "summary.json").read_text())["wall_s"] for n in names]
    print(f"campaign wall time (serial): median {statistics.median(ser):.1f} s, max {max(ser):.1f} s")
    overhead = t_cluster - sum(par) / args.workers
    print(f"campaigns' own wall times: serial sum {sum(ser):.1f} s, cluster sum {sum(par):.1f} s "
          f"({sum(par) / sum(ser):.2f}x: slow-down of a campaign when {args.workers} run at once, i.e. CPU contention)")
    print(f"Dask overhead (cluster wall - cluster sum / workers: start-up, scheduling, idle tail): {overhead:.1f} s; "
          f"on {args.workers} uncontended cores expect ~{t_serial / (sum(ser) / args.workers + overhead):.2f}x", flush=True)
    if args.skip_table:
        return 0

    t0 = time.perf_counter()
    full = run_sweep(proc, seeds, strategies, cluster_dir, workers=args.workers, progress=True)
    print(f"\nfull sweep: {len(full.runs)} campaigns ({len(full.skipped)} reused from the timing run) "
          f"in {time.perf_counter() - t0:.1f} s ({_loadavg()})")
    doc = full.document
    cap = proc.goal.max_experiments
    print(f"\nAdded experiments to reach mu-bar < {proc.goal.mu_target:g} ({proc.name}, cap {cap}, seeds 1..{args.seeds}; "
          f"'>{cap}' = not reached, 'E' = failed)")
    header = f"{'strategy':>13s} | " + " ".join(f"{s:>3d}" for s in seeds)
    print(header)
    print("-" * len(header))
    by_key = {(r["strategy"], r["seed"]): r for r in doc["runs"]}
    for s in strategies:
        cells = []
        for seed in seeds:
            r = by_key[(s, seed)]
            cells.append("E" if r.get("error") else (str(r["experiments_added"]) if r["reached_goal"] else f">{cap}"))
        print(f"{s:>13s} | " + " ".join(f"{c:>3s}" for c in cells))
    print()
    print(format_summary_table(doc))
    print(f"\nwrote {cluster_dir / 'sweep.json'} and {cluster_dir / 'sweep.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
