"""``setmem-hil sweep``: many campaigns (seeds x strategies x designs) on the simulated backend, on Dask.

::

    setmem-hil sweep --procedure FILE.toml --seeds A-B --strategies mu,log-sweep,random,max-reduction
                     [--designs h2,robust] --out DIR [--scheduler tcp://HOST:PORT] [--workers N] [--serial]
                     [--max-experiments N] [--quiet]

Each campaign (thesis Algorithm 5.1 until mu-bar < goal or the budget) is a task on an embedded
``LocalCluster`` (default) or the given ``dask scheduler``; ``--serial`` runs them in this
process. Finished campaigns are stored under ``DIR/runs/<strategy>-seed<N>/`` as they complete
and skipped when the sweep is run again, so an interrupted sweep resumes. ``DIR/sweep.json``
and ``DIR/sweep.png`` summarise the runs. See :mod:`setmem_hil.sweep.runner`.

Exit codes: 0 every campaign finished; 1 some campaign failed (each recorded with its error in
``DIR/runs/<...>/error.json`` and ``sweep.json``, the others complete); 2 bad arguments or
procedure; 130 interrupted (finished campaigns stay; run the same command again to resume).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from setmem_hil.errors import InputFormatError
from setmem_hil.io.procedure import STRATEGIES, Goal


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("sweep", help="many campaigns (seeds x input-design strategies x designs) on Dask, resumable",
                              description="Run the procedure's campaign for every seed and input-design strategy (on a local "
                              "Dask cluster, a scheduler, or serially), store each run in DIR/runs/, and write the per-strategy "
                              "statistics (DIR/sweep.json) and figure (DIR/sweep.png). Interrupted sweeps resume only what is missing.")
    p.add_argument("--procedure", required=True, metavar="FILE.toml", help="procedure file (backend kind \"sim\")")
    p.add_argument("--seeds", required=True, metavar="A-B", help="seeds, inclusive range A-B (or N, or a comma list)")
    p.add_argument("--strategies", default=",".join(STRATEGIES), metavar="LIST",
                   help=f"comma list of {', '.join(STRATEGIES)} (default: all)")
    p.add_argument("--designs", default=None, metavar="LIST",
                   help="comma list of h2, robust: compare the compensator designs as a third axis (runs named "
                   "<strategy>-<design>-seed<N>; default: the procedure's [design] method)")
    p.add_argument("--out", required=True, metavar="DIR", help="sweep directory (runs/, sweep.json, sweep.png)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                   help="a running dask scheduler (default: an embedded local cluster on 127.0.0.1)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local cluster: worker processes (default: CPU count); --scheduler: wait for N workers")
    p.add_argument("--serial", action="store_true", help="run the campaigns one by one in this process")
    p.add_argument("--max-experiments", type=int, default=None, metavar="N",
                   help="override the procedure's [goal] max_experiments")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.sweep.runner import format_summary_table, parse_designs, parse_seeds, parse_strategies, run_sweep

    seeds = parse_seeds(args.seeds)
    strategies = parse_strategies(args.strategies)
    designs = parse_designs(args.designs) if args.designs is not None else None
    if args.serial and args.scheduler:
        raise InputFormatError("--serial", "", "cannot be combined with --scheduler")
    procedure = load_procedure(args.procedure)
    if args.max_experiments is not None:
        if args.max_experiments < 0:
            raise InputFormatError("--max-experiments", "", f"expected >= 0, found {args.max_experiments}")
        procedure = dataclasses.replace(procedure, goal=Goal(mu_target=procedure.goal.mu_target,
                                                             max_experiments=args.max_experiments))
    try:
        result = run_sweep(procedure, seeds, strategies, args.out, scheduler=args.scheduler, workers=args.workers,
                           serial=args.serial, progress=not args.quiet, designs=designs)
    except TimeoutError as exc:
        print(f"setmem-hil: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        from setmem_hil.sweep.runner import read_run

        named = designs if designs not in (None, (procedure.design_method,)) else (None,)
        done = sum(1 for seed in seeds for s in strategies for d in named if (r := read_run(args.out, seed, s, d)) and not r.get("error"))
        print(f"setmem-hil: sweep interrupted with {done} of {len(seeds) * len(strategies) * len(named)} campaigns finished in "
              f"{args.out}; run the same command again to complete the others", file=sys.stderr)
        raise
    print(f"sweep {procedure.name}: {len(result.runs)} campaigns ({len(result.skipped)} already done, "
          f"{len(result.executed)} run now, {len(result.failed)} failed now) in {result.wall_s:.1f} s ({result.mode})")
    print(format_summary_table(result.document))
    print(f"wrote {result.out_dir / 'sweep.json'}" + ("" if not (result.out_dir / "sweep.png").exists()
                                                       else f" and {result.out_dir / 'sweep.png'}"))
    failures = [r for r in result.runs if r.get("error")]
    for r in failures:
        print(f"setmem-hil: campaign {r['strategy']}-seed{r['seed']} failed: {r['error']}", file=sys.stderr)
    return 1 if failures else 0
