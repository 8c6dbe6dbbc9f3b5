"""``setmem-hil controller RUN_DIR --out FILE [--format json|mat|sos|c] [--fs HZ [--delay-samples D]] [--iteration K]``.

Exports the compensator the campaign kept (the last iteration's, or iteration K's: after the
safeguard of eq. 5.12, so "previous-controller" iterations give the controller actually kept) in
physical units (rad/s), with the feedback sign (positive feedback, ``u = K y``) stated in every
format. The journal stores each iteration's compensator; journals written before it did are
upgraded on open and their compensators designed again from the stored intervals (H2 is
deterministic), where the iteration kept a new design. File contracts:
:mod:`setmem_hil.io.controller_file`; numerics: :mod:`setmem_hil.robust.controller_forms`.

With ``--delay-samples D`` (and ``--fs``) the loop as a real-time target runs it (the sections,
``D`` samples of computation delay, the zero-order hold) is analysed on the iteration's box with
the same mixed-mu bound (:mod:`setmem_hil.robust.implemented_loop`): the JSON gains
``implemented`` (``implemented_mu_bar`` beside the continuous ``mu_peak``), and a loop whose
certified implemented mu-bar is not below 1 is not exported: exit 2 naming the sample rate that would be needed.

Exit codes: 0 written; 2 bad arguments, a run with no iteration yet, or an implemented loop
that loses the guarantee (named).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from setmem_hil.errors import InputFormatError

FORMAT_CHOICES = ("json", "mat", "sos", "c")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "controller",
        help="export the compensator a run kept (JSON, .mat, second-order sections, C header)",
        description="Export the compensator of a run's last iteration (or --iteration K) in physical units, positive "
        "feedback u = K y: JSON (state space, poles, zeros), MATLAB .mat, second-order sections as CSV, or a C99 "
        "header with a step function. --fs gives the discrete form (Tustin prewarped at the mu-bar peak).",
        epilog="examples: setmem-hil controller runs/demo --out K.json --fs 1000;  "
        "setmem-hil controller runs/demo --out controller.h --fs 1000",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory (holds journal.sqlite)")
    p.add_argument("--out", required=True, metavar="FILE", help="output file; the format follows the extension "
                   "(.json, .mat, .csv = second-order sections, .h = C header) unless --format is given")
    p.add_argument("--format", choices=FORMAT_CHOICES, help="json, mat, sos (CSV of sections) or c (header); needs --fs for sos and c")
    p.add_argument("--fs", type=float, metavar="HZ", help="sample rate of the real-time target: adds the discrete form and sections")
    p.add_argument("--delay-samples", type=int, metavar="D", help="with --fs: the target's computation delay in samples (u[k] "
                   "from y[k-D]); analyse the loop as the target runs it (sections, delay, hold) and refuse one whose "
                   "certified mu-bar is not below 1")
    p.add_argument("--iteration", type=int, metavar="K", help="the compensator of iteration K (default: the last)")
    p.set_defaults(func=run)


def _error(where: str, problem: str) -> InputFormatError:
    return InputFormatError(where, "", problem)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.io.atomic_file import write_text_atomic
    from setmem_hil.io.controller_file import c_header, controller_document, format_for, mat_variables, sos_csv
    from setmem_hil.robust.controller_forms import second_order_sections, tustin_prewarped, zpk_of

    fmt = format_for(args.out, args.format)
    if fmt is None:
        raise _error("setmem-hil controller", f"--out {args.out}: give a .json, .mat, .csv or .h file, or --format")
    if fmt in ("sos", "c") and args.fs is None:
        raise _error("setmem-hil controller", f"--format {fmt} needs --fs HZ (the sections are discrete)")
    if args.fs is not None and not args.fs > 0:
        raise _error("setmem-hil controller", f"--fs {args.fs:g}: expected a positive sample rate in Hz")
    if args.delay_samples is not None and (args.fs is None or args.delay_samples < 0):
        raise _error("setmem-hil controller", f"--delay-samples {args.delay_samples}: needs --fs and a count >= 0")
    from setmem_hil.campaign.compensator import kept_controller

    record, K = kept_controller(args.run_dir, args.iteration)
    extra = {}
    if args.fs is not None:
        try:
            discrete = tustin_prewarped(K, args.fs, float(record.mu_peak_omega))
        except ValueError as exc:
            raise _error("setmem-hil controller", f"--fs {args.fs:g}: {exc}") from None
        sos, gain = second_order_sections(K, args.fs, float(record.mu_peak_omega))
        extra = {"discrete": discrete, "prewarp_rad_s": float(record.mu_peak_omega), "sos": sos, "sos_gain": gain}
    implemented = None if args.delay_samples is None else implemented_guarantee(args.run_dir, record, K, args.fs, args.delay_samples)
    doc = controller_document(iteration=record.k, mu_peak=record.mu_peak, continuous=K, zpk=zpk_of(K), design=record.design or "h2",
                              **extra)
    if implemented is not None:
        doc["implemented"] = implemented
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "json":
        write_text_atomic(out, json.dumps(doc, indent=1) + "\n")
    elif fmt == "sos":
        write_text_atomic(out, sos_csv(doc))
    elif fmt == "c":
        write_text_atomic(out, c_header(doc))
    else:
        import scipy.io

        scipy.io.savemat(str(out), mat_variables(doc))
    margin = f", margin {doc['margin']:.4g}" if doc.get("margin") else ""
    print(f"{out}: compensator of iteration {record.k} (order {K.nstates}, {doc['design']} design, mu-bar {record.mu_peak:.4g}{margin}), "
          "positive feedback u = K y"
          + (f", discrete at {args.fs:g} Hz" if args.fs else "")
          + ("" if implemented is None else f", implemented mu-bar {implemented['implemented_mu_bar']:.4g} (certified "
             f"{implemented['implemented_mu_bar_certified']:.4g}) with {args.delay_samples} samples of delay and the hold"))
    return 0


def implemented_guarantee(run_dir: str, record, K, fs_hz: float, delay_samples: int, command: str = "setmem-hil controller") -> dict:
    """The implemented loop's document (:class:`~setmem_hil.robust.implemented_loop.ImplementedLoop`),
    or :class:`InputFormatError` when its certified mu-bar is not below 1, naming the sample rate
    that would do."""
    from setmem_hil.campaign.compensator import kept_box, stored_procedure
    from setmem_hil.robust.implemented_loop import implemented_mu_bar, required_sample_rate

    model, gain = kept_box(record)
    weights = stored_procedure(run_dir).weights
    loop = implemented_mu_bar(model, weights, K, fs_hz, delay_samples, float(record.mu_peak_omega), gain)
    if not loop.guaranteed_mu_bar < 1.0:  # a NaN is no guarantee either
        needed = required_sample_rate(model, weights, K, delay_samples, float(record.mu_peak_omega), fs_hz, gain=gain)
        cost = ("an unstable sampled loop" if not loop.nominally_stable else
                f"mu-bar {loop.mu_bar:.4g} at {loop.mu_bar_omega_rad_s:.4g} rad/s, certified {loop.guaranteed_mu_bar:.4g}")
        rate = f"at least {needed:.4g} Hz would be needed" if needed else f"no rate up to {64 * fs_hz:g} Hz is enough"
        raise _error(command, f"--fs {fs_hz:g} --delay-samples {delay_samples}: the loop as the target runs it gives {cost} "
                     f"(continuous {record.mu_peak:.4g}): the delay and the hold cost the margin; {rate} with this delay")
    return {**loop.to_document(), "continuous_mu_bar": float(record.mu_peak)}
