"""``setmem-hil export DIR [--csv OUT/] [--uff FILE.uff]``: a run's journal as CSV files (see
:mod:`setmem_hil.io.export`) and its measured FRF as UFF 58 (:mod:`setmem_hil.io.uff_export`).
Without either option the CSV files go to ``DIR/csv``."""

from __future__ import annotations

import argparse

from setmem_hil.io.export import export_csv


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export",
        help="write a run's measurements, bounds and mu-bar per iteration as CSV",
        description="Write DIR's journal as CSV files: measurements.csv, data.csv, bounds.csv, mu.csv, "
        "iterations.csv, sensitivities.csv, candidates.csv, events.csv.",
    )
    p.add_argument("run_dir", metavar="DIR", help="run directory (holds journal.sqlite)")
    p.add_argument("--csv", metavar="OUT", help="output directory for the CSV files (created if missing; default DIR/csv "
                   "unless only --uff is given)")
    p.add_argument("--uff", metavar="FILE.uff", help="also (or only) write the measured FRF as UFF dataset 58, one record per output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from setmem_hil.cli.data_options import check_out_path

    paths = []
    uff = check_out_path(args.uff, "--uff") if args.uff else None
    if args.csv or not uff:
        paths += export_csv(args.run_dir, args.csv or str(Path(args.run_dir) / "csv"))
    if uff:
        from setmem_hil.io.journal import read_snapshot
        from setmem_hil.io.uff_export import export_uff

        paths.append(export_uff(args.run_dir, uff, _output_names(read_snapshot(args.run_dir).info)))
    for path in paths:
        print(path)
    return 0


def _output_names(info: dict) -> tuple[str, ...]:
    """The outputs' names from the run's stored procedure (empty when it no longer parses)."""
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.procedure_file import parse_procedure_text

    try:
        return tuple(parse_procedure_text(info["procedure_text"], "stored procedure").backend.output_order())
    except (ProcedureError, KeyError):
        return ()
