"""``setmem-hil campaign --procedure FILE.toml --backend sim --out DIR [--seed N] [--strategy S] [--design D]``.

Runs the iterative identification / control / experiment loop (thesis Algorithm 5.1) of a
procedure file and writes ``DIR/summary.json`` (``reached_goal``, ``final_mu_peak``,
``experiments_added``, ``wall_s``, ``iterations``: one ``{"k", "mu_peak", "next_omega",
"n_points", ...}`` per iteration) and ``DIR/journal.sqlite`` (every measurement, the bounds and
mu-bar of every iteration). ``--backend`` overrides the procedure's ``[backend] kind`` (the
procedure text stored with the run is then re-rendered with the new kind, so ``setmem-hil run
--resume DIR`` continues it). A ``DIR`` that already holds a journal is refused (exit 2);
continue such a run with ``setmem-hil run --resume DIR``.

The run itself is :func:`setmem_hil.cli.commands.run.start_run` (live progress, Ctrl-C handling:
exciter to zero, journal closed, exit 130).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from rich.console import Console

from setmem_hil.io.procedure import BACKENDS, DESIGN_METHODS, STRATEGIES
from setmem_hil.cli.campaign_options import DESIGN_HELP, SAFE_STOP

__all__ = ["register", "campaign", "print_iteration_table"]

CAMPAIGN_HELP = (
    "Run the campaign (thesis Algorithm 5.1) of a procedure file into DIR and print the figure-6-12 table. "
    "The same run as 'setmem-hil run', for scripts and sweeps of backends: --out is required, --backend "
    "overrides the procedure's backend kind. Resume a stopped campaign with 'setmem-hil run --resume DIR'."
)




def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("campaign", help="run a procedure's campaign into DIR, with a backend override (scripts)",
                              description=CAMPAIGN_HELP)
    p.add_argument("--procedure", required=True, metavar="FILE.toml", help="procedure file")
    p.add_argument("--backend", choices=BACKENDS, help="override the procedure's backend kind")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created; must not hold a journal)")
    p.add_argument("--seed", type=int, help="override the procedure's seed")
    p.add_argument("--strategy", choices=STRATEGIES, help="override the procedure's input-design strategy")
    p.add_argument("--design", choices=DESIGN_METHODS, help=DESIGN_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=campaign, interrupted=SAFE_STOP)


def campaign(args: argparse.Namespace) -> int:
    from setmem_hil.cli.commands.run import start_run
    from setmem_hil.io.procedure_file import load_procedure

    out = Path(args.out)  # start_run refuses a file, or a directory holding a journal
    procedure = load_procedure(args.procedure)
    if args.backend and args.backend != procedure.backend.kind:
        # the stored text must describe the backend actually used (resume re-reads it)
        procedure = dataclasses.replace(
            procedure, backend=dataclasses.replace(procedure.backend, kind=args.backend), source_text="",
        )
    console = Console(quiet=bool(args.quiet), soft_wrap=True)  # whole lines, also into a file (issue 40)
    outcome = start_run(procedure, out, seed=args.seed, strategy=args.strategy, console=console, design=args.design)
    print_iteration_table(outcome.summary, console)
    return 0


def print_iteration_table(summary: dict, console: Console) -> None:
    """The figure-6-12 table: mu-bar peak and the next frequency chosen, per iteration."""
    from rich.table import Table

    table = Table(title="mu-bar per iteration and the frequency chosen next (figure 6-12)")
    for name in ("k", "points", "mu-bar peak", "at rad/s", "next rad/s", "eq. 5.12", "design", "floor"):
        table.add_column(name, justify="right", no_wrap=name == "eq. 5.12")
    for it in summary.get("iterations", []):
        mu = it.get("mu_peak")
        nxt = it.get("next_omega")
        at = it.get("mu_peak_omega")
        table.add_row(
            str(it.get("k")), str(it.get("n_points")),
            "inf" if mu is None else f"{mu:.4f}",
            "-" if at is None else f"{at:.3f}",
            "-" if nxt is None else f"{nxt:.3f}",
            str(it.get("safeguard", "")),
            str(it.get("design", "")),
            ",".join(str(m) for m in it.get("floor_modes") or ()) or "-",
        )
    console.print(table)
    reached = summary.get("reached_goal")
    final = summary.get("final_mu_peak")
    margin = f"; margin {1.0 / float(final):.3f}" if reached and final else ""
    console.print(
        f"{'reached' if reached else 'did not reach'} mu-bar < {summary.get('goal_mu', 1.0):g} "
        f"with {summary.get('experiments_added')} added experiments "
        f"(final mu-bar {_mu_text(summary.get('final_mu_peak'))}, {summary.get('wall_s', 0.0):.1f} s{margin})",
        highlight=False,
    )


def _mu_text(mu) -> str:
    return "inf (nominal loop unstable)" if mu is None else f"{float(mu):.4f}"
