"""``setmem-hil identify-matrix --data FRF.csv --prior PRIOR.toml --out RESULT.json`` (public contract, issue 64).

The FRF matrix of a structure driven by several exciters and read by several sensors
(:mod:`setmem_hil.io.matrix_data_file`: ``sensor,exciter,omega,re,im,bound``), identified with
shared poles over every measured pair (:func:`~setmem_hil.identification.several_exciters.identify_matrix`).
The prior's modes give the frequency and damping bands; each pair's residue bounds are the
prior's made symmetric about zero (a pair's sign is not known beforehand). RESULT.json:
``{"kind": "frf-matrix", "sensors", "exciters", "modes": [{"a1", "a0", "b0", "b1", "verified",
"rank_one_consistent"}], "n_solves", "points"}`` with ``b0[k][l] = [lo, hi]`` for sensor ``k`` and
exciter ``l``; ``rank_one_consistent`` whether a real mode's box holds a rank-one residue matrix
(contracted by it), null for a mode whose ``b1`` is not fixed at zero.

Exit 0 on success (unverified modes are named); 2 on malformed input (file, line, column); 3 when
the pairs cannot share poles within their bounds (the message names the mode and the pairs).
"""

from __future__ import annotations

import argparse
import sys

from setmem_hil.cli.data_options import check_out_path, load_prior
from setmem_hil.io.result_file import write_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify-matrix",
                              help="guaranteed intervals of a structure's FRF matrix (several exciters and sensors, shared poles)",
                              description="Set-membership identification of every input-output pair with shared poles "
                              "(thesis appendix A; docs/several-exciters.md).")
    p.add_argument("--data", required=True, metavar="FRF.csv", help="header sensor,exciter,omega,re,im,bound")
    p.add_argument("--prior", required=True, metavar="PRIOR.toml", help="one [[mode]] table per mode")
    p.add_argument("--out", required=True, metavar="RESULT.json", help="where to write the intervals")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.identification.several_exciters import identify_matrix
    from setmem_hil.io.matrix_data_file import read_matrix_csv

    check_out_path(args.out)
    data = read_matrix_csv(args.data)
    prior = load_prior(args.prior)
    result = identify_matrix(data.columns, prior, data.sensors, data.exciters)
    doc = {"kind": "frf-matrix", **result.to_document(), "n_solves": result.n_solves, "points": data.n_points}
    write_json(doc, args.out)
    unverified = [i + 1 for i, verified in enumerate(result.verified) if not verified]
    print(f"identified {len(doc['modes'])} mode(s) with shared poles from {len(data.columns)} pair(s) of "
          f"{len(data.sensors)} sensor(s) x {len(data.exciters)} exciter(s), {data.n_points} points: {args.out}"
          + (f"; bounds of mode(s) {unverified} NOT verified" if unverified else ""))
    not_rank_one = [i + 1 for i, consistent in enumerate(result.rank_one_consistent) if consistent is False]
    if not_rank_one:
        print(f"setmem-hil: warning: mode(s) {not_rank_one}: no rank-one residue matrix (one real shape) fits the box; "
              "kept as identified (a repeated pole in one bracket, or a complex mode?)", file=sys.stderr)
    return 0
