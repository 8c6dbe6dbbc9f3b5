"""``setmem-hil discrepancy --data DATA.csv (--prior PRIOR.toml | --model MODEL.json) --out REPORT.json
[--plot FILE.png]`` (public contract).

Finds where model and data disagree, names the missing effect (or ``none`` / ``unexplained``),
re-identifies with it and writes ``{"disagreement_bands", "effects", "before", "after", ...}``
(see :mod:`setmem_hil.discrepancy.workflow`). ``--prior`` identifies the model first; ``--model`` takes a
model in the identify result format (zero-width intervals allowed). Exit 0 whatever the answer
(an infeasible identification is a finding here, reported in ``before``); 2 on malformed input.

Several ``--data`` (issue 25): the workflow runs per output (each output's prior entries, or the
model file's per-output residues) and the report says which output's data hold the missing
effect: ``"outputs": [{"name", <the one-output report>}, ...]``, every effect and band carries
``"output"``, and ``before``/``after`` are the worst over the outputs.
"""

from __future__ import annotations

import argparse
import sys

from setmem_hil.cli.data_options import add_data_options, check_out_path, load_output_priors, load_outputs, load_prior
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

    check_out_path(args.out)
    if args.plot:
        check_out_path(args.plot, "--plot")
    outputs = load_outputs(args)
    if len(outputs) > 1:
        return _run_outputs(args, outputs)
    data = outputs[0][1]
    progress = _progress_lines()
    if args.prior:
        report = discrepancy_from_prior(data, load_prior(args.prior), progress=progress)
    else:
        from setmem_hil.io.result_file import read_result

        report = check_discrepancy(data, read_result(args.model), None, progress=progress)
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


def _progress_lines():
    """Each step on stderr with the seconds since the command began (on real data the workflow
    takes minutes; a silent terminal looks hung)."""
    import time

    start = time.monotonic()

    def progress(text: str) -> None:
        print(f"discrepancy: [{time.monotonic() - start:6.1f} s] {text}", file=sys.stderr, flush=True)

    return progress


def _for_output(progress, name: str):
    """The progress lines of one output's workflow, named."""
    return lambda text: progress(f"{name}: {text}")


def _run_outputs(args: argparse.Namespace, outputs) -> int:
    """The workflow once per output; the report names the output of every finding."""
    from pathlib import Path

    from setmem_hil.discrepancy.workflow import check_discrepancy, discrepancy_from_prior

    progress = _progress_lines()
    if args.prior:
        priors, names = load_output_priors(args.prior, len(outputs))
        names = names or tuple(name for name, _ in outputs)
        reports = [discrepancy_from_prior(data, prior, progress=_for_output(progress, name))
                   for name, (_, data), prior in zip(names, outputs, priors)]
    else:
        from setmem_hil.io.result_file import read_result_outputs

        models = read_result_outputs(args.model, len(outputs))
        names = tuple(name for name, _ in outputs)
        reports = [check_discrepancy(data, model, None, progress=_for_output(progress, name)) for (name, data), model in zip(outputs, models)]
    doc = combined_document(names, [r.to_document() for r in reports])
    write_json(doc, args.out)
    if args.plot:
        from setmem_hil.discrepancy.plot import plot_discrepancy

        plot = Path(args.plot)
        for k, (name, report) in enumerate(zip(names, reports)):
            safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in name)
            plot_discrepancy(report, plot if k == 0 else plot.with_name(f"{plot.stem}-{safe}{plot.suffix}"))
    for name, report in zip(names, reports):
        found = ", ".join(e["name"] for e in report.effects) or "none"
        print(f"discrepancy: output {name}: {found}; worst normalised residual {report.before['max_normalized_residual']:.3g} -> "
              f"{report.after['max_normalized_residual']:.3g}", file=sys.stderr)
    return 0


def combined_document(names, docs: list[dict]) -> dict:
    """REPORT.json of several outputs: each output's report, and the findings tagged by output."""
    def worst(key: str) -> dict:
        residuals = [d[key].get("max_normalized_residual") for d in docs]
        finite = [r for r in residuals if r is not None]
        return {"max_normalized_residual": max(finite) if finite else None,
                "feasible": all(bool(d[key].get("feasible")) for d in docs)}

    return {
        "outputs": [{"name": name, **doc} for name, doc in zip(names, docs)],
        "effects": [{**effect, "output": name} for name, doc in zip(names, docs) for effect in doc["effects"]],
        "disagreement_bands": [[*band, name] for name, doc in zip(names, docs) for band in doc["disagreement_bands"]],
        "before": worst("before"),
        "after": worst("after"),
    }
