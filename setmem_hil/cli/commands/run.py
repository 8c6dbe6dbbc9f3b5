"""``setmem-hil run PROCEDURE.toml [--out DIR]`` and ``setmem-hil run --resume DIR``.

Runs a campaign (thesis Algorithm 5.1) from a procedure file with live progress, journaling
every measurement before the next dwell starts (``DIR/journal.sqlite``), and writes
``DIR/summary.json`` at the end. The application layer (journal, lock, signals, resume) is
:mod:`setmem_hil.campaign.session`; this module parses arguments and adds the terminal display.

Exit codes: 0 done (or already finished); 2 bad procedure or arguments; 3 data inconsistent
with the prior; 4 device fault (exciter at zero; resume once fixed); 130 interrupted.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from typing import TYPE_CHECKING

from setmem_hil.cli.campaign_options import DESIGN_HELP, SAFE_STOP
from setmem_hil.cli.live_options import add_live_options, live_view
from setmem_hil.errors import InputFormatError
from setmem_hil.io.procedure import DESIGN_METHODS, STRATEGIES

if TYPE_CHECKING:  # the campaign's modules load the numerics: imported when a run starts, not for --help
    from rich.console import Console

    from setmem_hil.campaign.journaled_run import RunOutcome
    from setmem_hil.io.procedure import Procedure

__all__ = ["register", "run", "start_run", "resume_run", "open_backend"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help="run a campaign from a procedure file (or resume one)",
        description="Run a campaign (thesis Algorithm 5.1) from a procedure file with live progress, journaling every "
        "measurement in DIR/journal.sqlite; or continue a stopped run with --resume DIR. Ctrl-C stops cleanly "
        "(exciter to zero, journal closed, exit 130).",
        epilog="examples: setmem-hil run procedures/serial_loopback.toml --out runs/serial;  "
        "setmem-hil run --resume runs/serial;  setmem-hil run --check procedures/beam_6_3_2.toml",
    )
    p.add_argument("procedure", nargs="?", metavar="PROCEDURE.toml", help="procedure file (see docs/procedures.md)")
    p.add_argument("--out", metavar="DIR", help="run directory (default: runs/<name>-<UTC time>)")
    p.add_argument("--resume", metavar="DIR", help="continue the run stored in DIR")
    p.add_argument("--procedure", dest="fixed_procedure", metavar="FIXED.toml",
                   help="with --resume: continue with this corrected procedure, reusing every stored measurement (journaled)")
    p.add_argument("--seed", type=int, help="override the procedure's seed (stored with the run)")
    p.add_argument("--strategy", choices=STRATEGIES, help="override the procedure's input-design strategy")
    p.add_argument("--design", choices=DESIGN_METHODS, help=DESIGN_HELP)
    p.add_argument("--check", action="store_true", help="validate the procedure and exit")
    p.add_argument("--report", action="store_true", help="write DIR/report.html when the run finishes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    add_live_options(p)
    p.set_defaults(func=run, interrupted=SAFE_STOP)


def _arguments_error(problem: str) -> InputFormatError:
    return InputFormatError("setmem-hil run", "arguments", problem)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console

    from setmem_hil.io.procedure_file import load_procedure

    console = Console(stderr=False, quiet=bool(args.quiet), soft_wrap=True)
    if args.resume:
        if args.procedure or args.out or args.seed is not None or args.strategy or args.design or args.check:
            raise _arguments_error("--resume DIR takes no procedure argument, --out, --seed, --strategy, --design or --check: the run's own "
                                   "are stored in its journal (a corrected procedure goes in --procedure FIXED.toml)")
        with live_view(args, Path(args.resume)) as live:
            outcome = resume_run(args.resume, console=console, procedure_path=args.fixed_procedure, **live)
    else:
        if not args.procedure:
            raise _arguments_error("give a procedure file, or --resume DIR")
        if args.fixed_procedure:
            raise _arguments_error("--procedure FIXED.toml goes with --resume DIR")
        if args.check and _checked_verification_procedure(args.procedure, console):
            return 0
        procedure = load_procedure(args.procedure)
        if args.check:
            from setmem_hil.campaign.preflight import preflight
            from setmem_hil.run.run_directory import describe_procedure

            preflight(procedure)
            describe_procedure(procedure, console)
            if procedure.backend.kind == "instruments":
                from setmem_hil.drivers.instruments.instrument_set import instrument_warnings

                for warning in instrument_warnings(procedure):
                    console.print(f"warning: {warning}", highlight=False, markup=False)
            console.print(f"{args.procedure}: OK", highlight=False)
            return 0
        from setmem_hil.run.run_directory import default_run_dir

        out = Path(args.out) if args.out else default_run_dir(procedure)
        with live_view(args, out) as live:
            outcome = start_run(procedure, out, seed=args.seed, strategy=args.strategy, console=console,
                                report_follows=bool(args.report), design=args.design, **live)
    if args.report:
        from setmem_hil.report.document import write_report

        path = write_report(outcome.run_dir)
        console.print(f"report: {path}", highlight=False)
    return 0


def open_backend(procedure: Procedure, seed: int):
    """The experiment the CLI runs: :func:`setmem_hil.experiment_factory.open_experiment`."""
    from setmem_hil.experiment_factory import open_experiment

    return open_experiment(procedure, seed)


def start_run(procedure: Procedure, run_dir: str | os.PathLike, *, seed: int | None = None, strategy: str | None = None,
              console: Console | None = None, report_follows: bool = False, design: str | None = None, **live) -> RunOutcome:
    """:func:`setmem_hil.campaign.session.start_run` with the terminal display (``report_follows``:
    the caller writes the report, so no hint how to)."""
    from rich.console import Console

    from setmem_hil.campaign import session
    from setmem_hil.cli.progress import terminal_display

    console = console or Console(soft_wrap=True)
    return session.start_run(procedure, run_dir, seed=seed, strategy=strategy, console=console,
                             opener=lambda p, s: open_backend(p, s), display=terminal_display(console),
                             quiet_report_hint=report_follows, design=design, **live)


def resume_run(run_dir: str | os.PathLike, *, console: Console | None = None, procedure_path=None, **live) -> RunOutcome:
    """:func:`setmem_hil.campaign.resume.resume_run` with the terminal display."""
    from rich.console import Console

    from setmem_hil.campaign.resume import resume_run as resume
    from setmem_hil.cli.progress import terminal_display

    console = console or Console(soft_wrap=True)
    return resume(run_dir, console=console, opener=lambda p, s: open_backend(p, s),
                              display=terminal_display(console), procedure_path=procedure_path, **live)


def _checked_verification_procedure(path: str, console) -> bool:
    """``run --check`` of a closed-loop verification procedure (a top-level ``[target]``): validated
    with its own schema (:mod:`setmem_hil.io.target_file`) and said what runs it."""
    from setmem_hil.io.target_file import is_verification_procedure, load_target_procedure

    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError:
        return False  # load_procedure names the problem
    if not is_verification_procedure(text):
        return False
    load_target_procedure(path)
    console.print(f"a closed-loop verification procedure: run it with setmem-hil verify RUN_DIR --procedure {path}", highlight=False)
    console.print(f"{path}: OK", highlight=False)
    return True
