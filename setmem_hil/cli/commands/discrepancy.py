"""``setmem-hil discrepancy --data DATA.csv (--prior PRIOR.toml | --model MODEL.json) --out REPORT.json
[--plot FILE.png]`` (public contract).

Finds where model and data disagree, names the missing effect (or ``none`` / ``unexplained``),
re-identifies with it and writes ``{"disagreement_bands", "effects", "before", "after", ...}``
(see :mod:`setmem_hil.discrepancy.workflow`). ``--prior`` identifies the model first; ``--model`` takes a
model in the identify result format (zero-width intervals allowed). Exit 0 whatever the answer
(an infeasible identification is a finding here, reported in ``before``); 2 on malformed input.
"""

from __future__ import annotations

import argparse
import sys

from setmem_hil.cli.data_options import add_data_options, load_data
from setmem_hil.io.result_file import write_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("discrepancy", help="find and name what the model lacks, add it, show the gap shrink",
                              description="Find where a model and measured data disagree, name the missing effect (or none / "
                              "unexplained), add it, re-identify and show the gap shrink (REPORT.json, optional figure).")
    add_data_options(p)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--prior", metavar="PRIOR.toml", help="identify the model from this prior first")
    src.add_argument("--model", metavar="MODEL.json", help="a model in the identify result format")
    p.add_argument("--out", required=True, metavar="REPORT.json", help="where to write the report")
    p.add_argument("--plot", metavar="FILE.png", help="figure: data, old and new model, residual bands")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.discrepancy.workflow import check_discrepancy, discrepancy_from_prior

    data = load_data(args)
    if args.prior:
        from setmem_hil.model.prior import read_prior

        report = discrepancy_from_prior(data, read_prior(args.prior))
    else:
        from setmem_hil.io.result_file import read_result

        report = check_discrepancy(data, read_result(args.model), None)
    write_json(report.to_document(), args.out)
    if args.plot:
        from setmem_hil.discrepancy.plot import plot_discrepancy

        plot_discrepancy(report, args.plot)
    names = ", ".join(e["name"] for e in report.effects) or "none"
    print(
        f"discrepancy: {names}; worst normalised residual {report.before['max_normalized_residual']:.3g} -> "
        f"{report.after['max_normalized_residual']:.3g}",
        file=sys.stderr,
    )
    return 0
