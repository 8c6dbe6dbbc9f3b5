"""``setmem-hil demo [--out DIR] [--seed N]``: the thesis section 6.3.2 campaign on the simulated beam.

Runs :func:`setmem_hil.io.procedure.default_procedure` (simulated cantilever, fully damped noise
bound plus W1, b1 = 0, 15 initial points around the three modes but off the peaks) until
mu-bar < 1, with live progress, and writes ``summary.json``, ``journal.sqlite`` and
``procedure.toml`` (and ``report.html`` when the report module is installed) into ``DIR``
(default ``./setmem-hil-demo-<UTC time>``). Prints the directory and the figure-6-12 table.
"""

from __future__ import annotations

import argparse
import dataclasses
from datetime import datetime, timezone
from pathlib import Path

from rich.console import Console
from setmem_hil.cli.main import SAFE_STOP


__all__ = ["register", "demo", "default_demo_dir"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="run the thesis section 6.3.2 campaign on the simulated beam", description=(
        "Run the thesis section 6.3.2 campaign on the simulated cantilever beam until mu-bar < 1, with progress, "
        "and write the journal, summary.json and report.html into DIR."))
    p.add_argument("--out", metavar="DIR", help="output directory (default ./setmem-hil-demo-<UTC time>)")
    p.add_argument("--seed", type=int, help="seed of the simulated noise (default: the procedure's)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=demo, interrupted=SAFE_STOP)


def default_demo_dir(now: datetime | None = None) -> Path:
    now = now or datetime.now(timezone.utc)
    return Path(f"setmem-hil-demo-{now.strftime('%Y%m%dT%H%M%SZ')}")


def demo(args: argparse.Namespace) -> int:
    from setmem_hil.cli.commands.campaign import print_iteration_table
    from setmem_hil.cli.commands.run import start_run
    from setmem_hil.io.procedure import default_procedure

    out = Path(args.out) if args.out else default_demo_dir()  # start_run refuses one holding a journal
    console = Console(quiet=bool(args.quiet))
    procedure = default_procedure()
    if args.seed is not None:
        procedure = dataclasses.replace(procedure, seed=int(args.seed))
    console.print("setmem-hil demo: thesis section 6.3.2 on the simulated cantilever beam", highlight=False)
    outcome = start_run(procedure, out, seed=args.seed, console=console)
    try:
        from setmem_hil.report.document import write_report
    except ModuleNotFoundError as exc:
        if exc.name != "setmem_hil.report.document":
            raise
        write_report = None
    if write_report is not None:
        path = write_report(outcome.run_dir)
        console.print(f"report: {path}", highlight=False)
    print_iteration_table(outcome.summary, console)
    console.print(f"outputs in {outcome.run_dir.resolve()}", highlight=False)
    return 0
