"""``setmem-hil analyze --model RESULT.json [--procedure FILE.toml] --out ANALYSIS.json`` (public contract).

Designs the H2 compensator for the model's midpoint (thesis section 6.3.1), computes the
mixed-mu upper bound on the default grid (refined around the peak), its lower bound and the
mu-sensitivities (section 4.2.2), and writes

``{"mu_peak", "mu_peak_omega", "mu_lower_peak", "omega", "mu", "sensitivities", "controller_order"}``; sensitivities are keyed ``<param>_<mode>`` (modes from 1), fixed parameters
absent. Weights come from the procedure file's ``[weights]`` table, else the thesis's.
Exit 0 on success, 2 on malformed input.
"""

from __future__ import annotations

import argparse
import math

from setmem_hil.io.result_file import read_result, write_json
from setmem_hil.io.analysis_inputs import check_model, weights_for

def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("analyze", help="H2 design, mixed-mu robust performance and mu-sensitivities of a model",
                              description="Design the H2 compensator for the model's midpoint and compute the mixed-mu upper "
                              "bound of robust performance (D and G scales), its peak and the mu-sensitivities (ANALYSIS.json).")
    p.add_argument("--model", required=True, metavar="RESULT.json", help="interval model (identify result format)")
    p.add_argument("--procedure", metavar="FILE.toml", help="procedure file, or a file with only a [weights] table; its weights are used")
    p.add_argument("--out", required=True, metavar="ANALYSIS.json", help="where to write the analysis")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.cli.data_options import check_out_path
    from setmem_hil.robust.analysis import analyze_robust_performance

    check_out_path(args.out)
    model = read_result(args.model)
    check_model(model, args.model)
    weights = weights_for(args.procedure)
    result = analyze_robust_performance(model, weights)
    write_json(result.to_document(), args.out)
    top = sorted(result.sensitivities.items(), key=lambda kv: -kv[1])[:3]
    mu = "inf (nominal loop unstable)" if not math.isfinite(result.mu_peak) else f"{result.mu_peak:.4f}"
    print(f"mu-bar peak {mu} at {result.mu_peak_omega:.4g} rad/s ({result.mu_peak_omega / (2 * math.pi):.4g} Hz); "
          f"most sensitive: {', '.join(f'{k} {v:.3g}' for k, v in top) or '-'}; {args.out}")
    return 0
