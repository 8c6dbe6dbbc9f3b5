"""``setmem-hil reprocess DIR [--out FILE.json]``: recompute every measurement of a run from its
raw records (``DIR/raw.h5``) and compare with the journal (:mod:`setmem_hil.campaign.reprocess`).

Exit codes: 0 every point and bound agree (relative 1e-9); 3 a point differs (the message names
its ``seq``); 2 the raw records are missing (or unreadable)."""

from __future__ import annotations

import argparse

EXIT_DIFFERS = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "reprocess",
        help="recompute every measurement from its raw record and compare with the journal",
        description="Recompute every measurement of DIR from DIR/raw.h5 with the stored settings and compare each point "
        "and bound with the journal's (relative 1e-9). Exit 0 when all agree, 3 naming the first measurement (seq) "
        "that differs, 2 when the raw records are missing.",
    )
    p.add_argument("run_dir", metavar="DIR", help="run directory (holds journal.sqlite and raw.h5)")
    p.add_argument("--out", metavar="FILE.json", help="write the comparison of every measurement as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import sys

    from setmem_hil.campaign.reprocess import reprocess_run
    from setmem_hil.cli.data_options import check_out_path
    from setmem_hil.io.atomic_file import write_json_atomic

    out = check_out_path(args.out, "--out") if args.out else None
    report = reprocess_run(args.run_dir)
    if out:
        write_json_atomic(report.to_document(), out)
    first = report.first_difference
    n = len(report.measurements)
    uncommitted = f"; {len(report.uncommitted)} record(s) of points never committed ignored" if report.uncommitted else ""
    if first is not None:
        differing = sum(1 for m in report.measurements if not m["agrees"])
        print(f"setmem-hil: reprocess {args.run_dir}: measurement seq {first['seq']} at {first['omega_rad_s']:.6g} rad/s "
              f"{first['problem']} ({differing} of {n} differ){uncommitted}", file=sys.stderr)
        return EXIT_DIFFERS
    print(f"{args.run_dir}: {n} measurements recomputed from {report.records} raw records agree with the journal "
          f"(largest relative difference {report.largest_relative_difference:.2g}){uncommitted}")
    return 0
