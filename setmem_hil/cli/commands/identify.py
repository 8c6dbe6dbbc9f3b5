"""``setmem-hil identify --data DATA.csv [--data ...] --prior PRIOR.toml --out RESULT.json`` (public contract).

Exit 0 on success; 2 on malformed input (the message names file, line or key); 3 when the data
are inconsistent with the prior (the message names the frequencies; with several outputs also
the output and the mode), and when no parameter point of the box was found to fit every point
(RESULT.json is written, its ``witness`` holds the best fit; issue 62). With ``--reject-outliers`` (thesis section 7.2) the fewest points
needed to regain consistency are dropped and reported (one output so far).

Several ``--data`` (issue 25): one output per file, in the order given; the modes' poles are
shared and each output has its own residues (:func:`~setmem_hil.identification.algorithm.identify_outputs`).
"""

from __future__ import annotations

import argparse
import sys

from setmem_hil.cli.data_options import add_data_options, check_out_path, load_output_priors, load_outputs, load_prior
from setmem_hil.identification.algorithm import identify
from setmem_hil.io.result_file import write_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("identify", help="guaranteed interval bounds of a modal model from frequency data",
                              description="Set-membership identification (thesis chapter 3): guaranteed intervals of every "
                              "modal parameter consistent with the data, its error bounds and the prior (RESULT.json).")
    add_data_options(p)
    p.add_argument("--prior", required=True, metavar="PRIOR.toml", help="one [[mode]] table per mode")
    p.add_argument("--out", required=True, metavar="RESULT.json", help="where to write the intervals")
    p.add_argument("--reject-outliers", action="store_true",
                   help="drop the fewest points needed to regain consistency (thesis 7.2) and report them; at most 5 points "
                        "and 40 trial identifications (progress on stderr), else exit 3: the prior does not fit the data")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_out_path(args.out)
    outputs = load_outputs(args)
    if len(outputs) > 1:
        return _run_outputs(args, outputs)
    data = outputs[0][1]
    prior = load_prior(args.prior)
    if args.reject_outliers:
        from setmem_hil.identification.outlier_rejection import identify_rejecting_outliers

        result, rejected = identify_rejecting_outliers(data, prior, progress=lambda text: print(text, file=sys.stderr, flush=True))
        doc = result.to_document()
        doc["rejected_points"] = [{"omega": float(w)} for w in rejected]
        if rejected:
            print(f"rejected {len(rejected)} point(s) at omega = {', '.join(f'{w:.6g}' for w in rejected)} rad/s", file=sys.stderr)
    else:
        doc = identify(data, prior).to_document()
    _add_exact_ratios(doc, data, prior)
    write_json(doc, args.out)
    unverified = [i + 1 for i, m in enumerate(doc["modes"]) if m.get("verified") is False]
    used = len(data.omega_rad_s) - len(doc.get("rejected_points", []))
    dropped = f" ({len(doc['rejected_points'])} rejected)" if doc.get("rejected_points") else ""
    print(f"identified {len(doc['modes'])} mode(s) from {used} points{dropped} in {doc['iterations']} iteration(s): "
          f"{args.out}" + (f"; bounds of mode(s) {unverified} NOT verified (see unverified_reason)" if unverified else ""))
    return _witness_exit(doc)


def _witness_exit(doc: dict) -> int:
    """Exit 3 when no parameter point of the box was found to fit (issue 62): the box is written
    (nothing measured is lost) but nothing in it is known to fit; the message names the best fit's
    misfit and the points that bind it."""
    witness = doc.get("witness")
    if witness is None or witness["fits"]:
        return 0
    shown = ", ".join(f"{w:.6g}" for w in witness["binding_omega_rad_s"][:6])
    print(f"error: no parameter point of the identified box was found to fit every point: the best fit "
          f"({witness['starts']} starts) misses by {witness['misfit']:.3g} times the bound at omega = {shown} rad/s "
          "(check those measurements and bounds, or the model: a mode or effect missing?)", file=sys.stderr)
    return 3


def _add_exact_ratios(doc: dict, data, prior) -> None:
    """``modes[i].exact_ratio`` (issue 47): each interval over the linearised exact feasible set's
    extent (linearised at a point of the box that fits), so a user sees where the method is
    conservative (thesis 3.6)."""
    if prior.residuals.enabled or doc.get("rejected_points"):
        return  # the reference models neither residual terms nor rejected points
    from setmem_hil.identification.exact_ratio import exact_ratios
    from setmem_hil.io.result_file import parse_result_mapping

    model = parse_result_mapping(doc, "result")
    box = prior.initial_bounds()
    for mode, ratio in zip(doc["modes"], exact_ratios(data.omega_rad_s, data.response, data.bound, model.lower,
                                                        model.upper, box.lower, box.upper)):
        mode["exact_ratio"] = ratio


def _run_outputs(args: argparse.Namespace, outputs) -> int:
    """Several outputs with shared poles (issue 25)."""
    from setmem_hil.identification.algorithm import identify_outputs

    priors, names = load_output_priors(args.prior, len(outputs))
    names = names or tuple(name for name, _ in outputs)
    datas, rejected = [d for _, d in outputs], []
    if args.reject_outliers:  # each output's outliers alone (thesis 7.2), then the outputs together
        datas, rejected = _without_outliers(datas, priors, names)
    result = identify_outputs(datas, priors, list(names))
    doc = result.to_document()
    if args.reject_outliers:
        doc["rejected_points"] = rejected
    write_json(doc, args.out)
    unverified = [i + 1 for i, m in enumerate(doc["modes"]) if m.get("verified") is False]
    points = ", ".join(f"{name} {len(d.omega_rad_s)}" for name, d in zip(names, datas))
    print(f"identified {len(doc['modes'])} mode(s) with shared poles from {len(outputs)} outputs ({points} points) in "
          f"{doc['iterations']} iteration(s): {args.out}" + (f"; bounds of mode(s) {unverified} NOT verified (see unverified_reason)" if unverified else ""))
    return 0


def _without_outliers(datas, priors, names):
    """Every output's data without the points ``--reject-outliers`` sets aside for it alone, and
    the list of those points (``{"omega", "output"}``)."""
    import numpy as np

    from setmem_hil.errors import InconsistentDataError
    from setmem_hil.identification.outlier_rejection import identify_rejecting_outliers

    kept, rejected = [], []
    for data, prior, name in zip(datas, priors, names):
        try:
            _, dropped = identify_rejecting_outliers(data, prior, progress=lambda text, name=name: print(f"{name}: {text}", file=sys.stderr, flush=True))
        except InconsistentDataError as exc:
            raise InconsistentDataError(f"output {name}: {exc}", omegas_rad_s=exc.omegas_rad_s, mode_index=exc.mode_index) from None
        keep = np.flatnonzero(~np.isin(data.omega_rad_s, dropped))
        kept.append(data.subset(keep))
        rejected += [{"omega": float(w), "output": name} for w in dropped]
        if dropped:
            print(f"{name}: rejected {len(dropped)} point(s) at omega = {', '.join(f'{w:.6g}' for w in dropped)} rad/s", file=sys.stderr)
    return kept, rejected
