"""``setmem-hil export DIR --csv OUT/``: a run's journal as CSV files (see :mod:`setmem_hil.io.export`)."""

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
    p.add_argument("--csv", metavar="OUT", help="output directory for the CSV files (created if missing; default DIR/csv)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    out = args.csv or str(Path(args.run_dir) / "csv")
    paths = export_csv(args.run_dir, out)
    for path in paths:
        print(path)
    return 0
