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
from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.io.result_file import read_result, write_json
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

_WEIGHT_KEYS = ("w1_num", "w1_den", "w2_num", "w2_den", "w2_extra_pole_rad_s")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("analyze", help="H2 design, mixed-mu robust performance and mu-sensitivities of a model",
                              description="Design the H2 compensator for the model's midpoint and compute the mixed-mu upper "
                              "bound of robust performance (D and G scales), its peak and the mu-sensitivities (ANALYSIS.json).")
    p.add_argument("--model", required=True, metavar="RESULT.json", help="interval model (identify result format)")
    p.add_argument("--procedure", metavar="FILE.toml", help="procedure file, or a file with only a [weights] table; its weights are used")
    p.add_argument("--out", required=True, metavar="ANALYSIS.json", help="where to write the analysis")
    p.set_defaults(func=run)


def _weights_from_table(path: str) -> Weights:
    """Fallback reader of the ``[weights]`` table when the procedure loader is unavailable."""
    import tomllib

    try:
        doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputFormatError(path, "", f"cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFormatError(path, "", f"invalid TOML: {exc}") from None
    table = doc.get("weights", {})
    if not isinstance(table, dict):
        raise InputFormatError(path, "[weights]", f"expected a table, found {type(table).__name__}")
    kwargs = {}
    for key, value in table.items():
        if key not in _WEIGHT_KEYS:
            raise InputFormatError(path, f"[weights] key '{key}'", f"unknown key; expected one of {', '.join(_WEIGHT_KEYS)}")
        if key == "w2_extra_pole_rad_s":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise InputFormatError(path, f"[weights] key '{key}'", f"expected a non-negative number, found {value!r}")
            kwargs[key] = float(value) or None
        else:
            if not isinstance(value, list) or not value or not all(
                isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value
            ):
                raise InputFormatError(path, f"[weights] key '{key}'", f"expected a list of numbers, found {value!r}")
            kwargs[key] = tuple(float(c) for c in value)
    return Weights(**kwargs) if kwargs else THESIS_WEIGHTS


def weights_for(procedure_path: str | None) -> Weights:
    """Weights of a procedure file (``[weights]``; a file with only that table is enough), or the
    thesis's when no file is given. A full procedure is validated as a whole."""
    if procedure_path is None:
        return THESIS_WEIGHTS
    from setmem_hil.model.prior import load_toml

    if "mode" in load_toml(procedure_path):
        from setmem_hil.io.procedure_file import load_procedure

        return load_procedure(procedure_path).weights
    return _weights_from_table(procedure_path)


def check_model(model, source: str) -> None:
    """Refuse a model the analysis cannot mean: non-finite or absurd bounds, natural frequencies
    not bounded away from zero (``a0 <= 0``), negative damping (``a1 < 0``)."""
    from setmem_hil.model.frequency_data import MAX_MAGNITUDE
    from setmem_hil.model.modal_model import PARAM_NAMES

    for i in range(model.n_modes):
        for j, name in enumerate(PARAM_NAMES):
            lo, hi = float(model.lower[i, j]), float(model.upper[i, j])
            where = f"mode {i + 1} {name}"
            if not (math.isfinite(lo) and math.isfinite(hi)) or max(abs(lo), abs(hi)) > MAX_MAGNITUDE:
                raise InputFormatError(source, where, f"[{lo:g}, {hi:g}]: the analysis needs finite bounds below {MAX_MAGNITUDE:g}")
        if model.lower[i, 1] <= 0:
            raise InputFormatError(source, f"mode {i + 1} a0", f"lower bound {model.lower[i, 1]:g} must be > 0 (a0 = omega_n^2 of a vibration mode)")
        if model.lower[i, 0] < 0:
            raise InputFormatError(source, f"mode {i + 1} a1", f"lower bound {model.lower[i, 0]:g} must be >= 0 (a1 = 2 zeta omega_n, no negative damping)")


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
