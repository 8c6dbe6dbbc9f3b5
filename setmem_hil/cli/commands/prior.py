"""``setmem-hil prior --data DATA(.csv|.uff) --modes N [--band LO_HZ HI_HZ] --out PRIOR.toml``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from setmem_hil.cli.data_options import add_data_options, check_out_path, load_outputs
from setmem_hil.errors import InputFormatError

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "prior", help="propose a prior (PRIOR.toml) from a measured FRF",
        description="Estimate poles (LSCF, sdypy-EMA) and residues (least squares) of N modes from a measured FRF and "
        "write them, widened into brackets, as PRIOR.toml, with a stability diagram (PRIOR-stability.png). The file "
        "names every assumption; identification is guaranteed relative to this prior.")
    add_data_options(p)
    p.add_argument("--modes", required=True, type=int, metavar="N", help="number of [[mode]] tables (a low pseudo-mode for what lies below the band counts as one)")
    p.add_argument("--band", nargs=2, type=float, metavar=("LO_HZ", "HI_HZ"), help="frequency band in Hz (default: the whole file)")
    p.add_argument("--residuals", choices=("none", "lower", "upper", "both"), default="none", help="add a [residuals] table")
    p.add_argument("--residues", choices=("auto", "real", "complex"), default="auto",
                   help="real: b1 = 0 (receptance of proportionally damped modes); complex: b1 bracketed too; auto "
                   "(default): real unless its estimate misses the data by more than the bound and the complex one "
                   "misses it less")
    p.add_argument("--out", required=True, metavar="PRIOR.toml", help="where to write the prior")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """One output, or several on one frequency axis (issue 25): common poles by LSCF over every
    output, residue brackets per output, one PRIOR.toml with ``outputs = [...]`` and arrays."""
    from setmem_hil.estimation.modal_estimate import estimate_common_modes
    from setmem_hil.io.atomic_file import write_text_atomic
    from setmem_hil.io.prior_proposal import format_prior_proposal
    from setmem_hil.report.stability_diagram import plot_stability_diagram

    out = check_out_path(args.out)
    if args.modes < 1:
        raise InputFormatError("setmem-hil prior", "--modes", f"expected at least 1, found {args.modes}")
    band = None
    if args.band:
        lo, hi = args.band
        if not (0 < lo < hi and math.isfinite(hi)):
            raise InputFormatError("setmem-hil prior", "--band", f"expected 0 < LO_HZ < HI_HZ, found {lo:g} {hi:g}")
        band = (2 * math.pi * lo, 2 * math.pi * hi)
    residuals = {"none": (), "lower": ("lower",), "upper": ("upper",), "both": ("lower", "upper")}[args.residuals]
    outputs = load_outputs(args)
    if len(outputs) > 1 and residuals:
        raise InputFormatError("setmem-hil prior", "--residuals", "residual terms with several --data files are not supported "
                               "yet (identify takes them with one output only)")
    files = args.data if isinstance(args.data, list) else [args.data]
    try:
        estimates = estimate_common_modes([d for _, d in outputs], args.modes, band, residuals=residuals)
    except ValueError as exc:
        raise InputFormatError(", ".join(files), "--modes/--band", str(exc)) from None
    estimates, complex_reason = _choose_residues(args.residues, [d for _, d in outputs], estimates)
    named = [(name, est) for (name, _), est in zip(outputs, estimates)] if len(outputs) > 1 else None
    source = Path(files[0]).name if named is None else " and ".join(name for name, _ in named)
    brackets = _no_wider_than_each_alone(args.residues, outputs, estimates, complex_reason, band, residuals) if named else None
    try:
        text = format_prior_proposal(estimates[0], source, residuals, outputs=named, complex_reason=complex_reason, brackets=brackets)
    except ValueError as exc:
        raise InputFormatError(", ".join(files), "--modes", str(exc)) from None
    write_text_atomic(out, text)
    if complex_reason is not None:
        print(f"prior: complex residues (b1 bracketed): {complex_reason}")
    figure = plot_stability_diagram(estimates[0], outputs[0][1], out.with_name(out.stem + "-stability.png"))
    _summarise(out, figure, estimates[0], named, complex_reason is not None)
    return 0


def _no_wider_than_each_alone(choice: str, outputs, estimates, complex_reason, band, residuals) -> list[list[dict]]:
    """Each output's residue brackets in the joint proposal, none wider than the output's own
    single-output proposal (issue 40, item 8: on a third point of the real beam the joint
    proposal's brackets were wider, and the shared frequency intervals up to 1.35 x wider than
    point 1 alone). Each output is proposed alone as ``prior --data`` that one file would."""
    from setmem_hil.estimation.modal_estimate import estimate_common_modes
    from setmem_hil.io.prior_proposal import no_wider_than_alone, output_brackets

    out = []
    for (_, data), joint in zip(outputs, estimates):
        try:
            alone = estimate_common_modes([data], len(joint.modes), band, residuals=residuals)
        except ValueError:  # this output alone cannot be estimated: its joint brackets stand
            out.append(output_brackets(joint, complex_reason is not None))
            continue
        alone, alone_reason = _choose_residues(choice, [data], alone)
        out.append(no_wider_than_alone(joint, output_brackets(joint, complex_reason is not None), alone[0],
                                       output_brackets(alone[0], alone_reason is not None)))
    return out


def _choose_residues(choice: str, datas, estimates):
    """The estimates to propose from, and why complex residues were chosen (None: real).

    ``auto`` keeps real residues (``b1 = 0``) while their estimate fits every output within its
    bound, and otherwise brackets ``b1`` too (our choice, issue 25's real-beam data: the
    least-squares estimate at fixed poles misses by 1.8 x the bound either way, but the set of
    parameters within the prior is not empty once the residues may be complex, while with
    ``b1 = 0`` identify exits 3)."""
    from setmem_hil.estimation.modal_estimate import with_complex_residues

    if choice == "real":
        return estimates, None
    worst_real = max(e.max_normalized_residual for e in estimates)
    if choice == "auto" and not worst_real > 1.0:
        return estimates, None
    reason = ("--residues complex" if choice == "complex" else
              f"the real-residue estimate misses the data by up to {worst_real:.3g} x the bound (--residues real keeps b1 = 0)")
    return with_complex_residues(datas, estimates), reason


def _summarise(out: Path, figure, estimate, named, complex_residues: bool) -> None:
    """The proposed modes on stdout; the flagged modes and a misfit on stderr (issue 25: both
    used to be written silently)."""
    from setmem_hil.io.prior_proposal import misfit_advice, suspicious_modes

    flags = dict(suspicious_modes(estimate))
    for i, m in enumerate(estimate.modes):
        kind = "low pseudo-mode" if m.low_pseudo_mode else f"{m.omega_n_rad_s / (2 * math.pi):.6g} Hz, zeta {m.zeta:.3g}"
        b0 = f"{m.b0:.4g}" if named is None else ", ".join(f"{name} {e.modes[i].b0:.4g}" for name, e in named)
        print(f"  mode: {kind}, b0 {b0}" + (f"  <- CHECK: {flags[i]}" if i in flags else ""))
    worst_name, worst = max(named or [("", estimate)], key=lambda t: t[1].max_normalized_residual)
    modes = f"{len(estimate.modes)} modes" if named is None else f"{len(estimate.modes)} common modes, {len(named)} outputs"
    which = f" ({worst_name})" if named else ""
    print(f"prior: {out} ({modes}; worst normalised residual of the estimate {worst.max_normalized_residual:.3g}{which}); "
          f"stability diagram: {figure}")
    for i, reason in flags.items():
        m = estimate.modes[i]
        print(f"setmem-hil: warning: proposed mode {i + 1} at {m.omega_n_rad_s / (2 * math.pi):.6g} Hz: {reason}; likely a "
              "computational mode of the fit: look at the stability diagram, and try one mode fewer or a --band without it",
              file=sys.stderr)
    advice = misfit_advice(worst, complex_residues)
    if advice:
        print(f"setmem-hil: warning: {f'output {worst_name}: ' if named else ''}{advice}", file=sys.stderr)
