"""``setmem-hil report DIR``: write ``DIR/report.html`` with PNG figures (see :mod:`setmem_hil.report.document`)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "report",
        help="write DIR/report.html: figures 6-12, 6-13, 6-14, sample transfer functions, pole-zero patterns, interval tables",
        description="Write DIR/report.html (plain HTML, PNG figures next to it) from the run's journal.",
    )
    p.add_argument("run_dir", metavar="DIR", help="run directory (holds journal.sqlite)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.report.document import write_report

    print(write_report(args.run_dir))
    return 0
