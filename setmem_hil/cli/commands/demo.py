"""``setmem-hil demo [--out DIR] [--seed N]``: the thesis section 6.3.2 campaign on the simulated beam.

Runs :func:`setmem_hil.io.procedure.default_procedure` (simulated cantilever, fully damped noise
bound plus W1, b1 = 0, 15 initial points around the three modes but off the peaks) until
mu-bar < 1, with live progress, and writes ``summary.json``, ``journal.sqlite`` and
``procedure.toml`` and ``report.html`` into ``DIR``
(default ``./setmem-hil-demo-<UTC time>``). Prints the directory and the figure-6-12 table.
"""

from __future__ import annotations

import argparse
import dataclasses
from datetime import datetime, timezone
from pathlib import Path

from rich.console import Console
from setmem_hil.cli.live_options import add_live_options, live_view
from setmem_hil.cli.campaign_options import SAFE_STOP
from setmem_hil.cli.campaign_options import DESIGN_HELP
from setmem_hil.io.procedure import DESIGN_METHODS


__all__ = ["register", "demo", "default_demo_dir"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the thesis section 6.3.2 campaign on the simulated beam", description=(
        "Run the thesis section 6.3.2 campaign on the simulated cantilever beam until mu-bar < 1, with progress, "
        "and write the journal, summary.json and report.html into DIR."))
    p.add_argument("--out", metavar="DIR", help="output directory (default ./setmem-hil-demo-<UTC time>)")
    p.add_argument("--seed", type=int, help="seed of the simulated noise (default: the procedure's)")
    p.add_argument("--design", choices=DESIGN_METHODS, help=DESIGN_HELP)
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_live_options(p)
    p.set_defaults(func=demo, interrupted=SAFE_STOP)


def packaged_demo_procedure():
    """The shipped ``procedures/beam_6_3_2.toml`` (packaged with the code), so the run stores the
    file's own text, comments included; numerically it is :func:`setmem_hil.io.procedure.default_procedure`."""
    from importlib.resources import files

    from setmem_hil.io.procedure_file import parse_procedure_text

    text = files("setmem_hil").joinpath("procedures/beam_6_3_2.toml").read_text(encoding="utf-8")
    return parse_procedure_text(text, "beam_6_3_2.toml")


def default_demo_dir(now: datetime | None = None) -> Path:
    now = now or datetime.now(timezone.utc)
    return Path(f"setmem-hil-demo-{now.strftime('%Y%m%dT%H%M%SZ')}")


def demo(args: argparse.Namespace) -> int:
    from setmem_hil.cli.commands.campaign import print_iteration_table
    from setmem_hil.cli.commands.run import start_run

    out = Path(args.out) if args.out else default_demo_dir()  # start_run refuses one holding a journal
    console = Console(quiet=bool(args.quiet), soft_wrap=True)  # whole lines, also into a file (issue 40)
    procedure = packaged_demo_procedure()
    if args.seed is not None:
        procedure = dataclasses.replace(procedure, seed=int(args.seed))
    console.print("setmem-hil demo: thesis section 6.3.2 on the simulated cantilever beam", highlight=False)
    with live_view(args, out) as live:
        outcome = start_run(procedure, out, seed=args.seed, console=console, report_follows=True, design=args.design, **live)
    from setmem_hil.report.document import write_report

    console.print(f"report: {write_report(outcome.run_dir)}", highlight=False)
    print_iteration_table(outcome.summary, console)
    console.print(f"outputs in {outcome.run_dir.resolve()}", highlight=False)
    return 0
