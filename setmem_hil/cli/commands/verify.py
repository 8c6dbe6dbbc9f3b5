"""``setmem-hil verify RUN_DIR --procedure TARGET.toml --out DIR``: the compensator on the rig.

Loads the compensator a run kept into the real-time target of TARGET.toml (``[target]``:
:mod:`setmem_hil.io.target_file`), engages it in steps of gain, each certified before it is
engaged (the implemented mu-bar with the target's sections, delay and hold), measures the closed
loop by injecting sines at the summing junction, and checks every point against the box's
guaranteed prediction (:mod:`setmem_hil.verify.plan`, a plan on the run engine).

Output: ``DIR/verify.json`` (the plan's document, :mod:`setmem_hil.verify.document`; also copied
to ``RUN_DIR/verify.json``, which the run's report shows), ``DIR/verify.png`` (the
predicted band of ``|S|`` and the measured points), ``DIR/journal.sqlite`` and ``DIR/raw.h5``
(the campaign's kinds of journal and raw store, :mod:`setmem_hil.verify.session`), and for their
earlier readers ``DIR/journal.jsonl`` (every document, one JSON line each, flushed as written) and
``DIR/records/`` (each point's injection, drive and response, ``<seq>.npz``; the rig at rest
before engaging, ``baseline.npz``). A later ``verify`` into the same directory appends: its journal
entries follow the earlier ones and its records are numbered after theirs (its rig at rest
``baseline-<seq>.npz``); nothing stored is overwritten.

Exit codes: 0 every point inside its prediction; 3 a point outside (named); 4 a target or
instrument fault, or a loop that grew or did not settle (the target bypassed and the generator off, confirmed);
2 bad input, or a loop whose certified implemented mu-bar is not below 1 (never engaged; the sample rate needed
is named); 130 interrupted (bypassed, confirmed).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

EXIT_OUTSIDE = 3


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "verify",
        help="load the compensator into a real-time target, engage it in steps and check the closed loop against the box",
        description="Run a run's compensator on the real-time target of TARGET.toml: load it (checksum read back), engage it "
        "in certified gain steps, inject sines at the summing junction, measure S = u/r and G = y/u with guaranteed bounds, "
        "and check each point against the box's prediction. Exit 0 all inside, 3 a point outside, 4 a fault (bypassed), "
        "2 bad input or a sample rate too low for the guarantee.",
        epilog="example: setmem-hil verify runs/demo --procedure procedures/closed_loop_emulated.toml --out runs/demo-verify",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="the campaign's run directory (holds journal.sqlite)")
    p.add_argument("--procedure", required=True, metavar="TARGET.toml", help="the target and the measurement ([target], [verify])")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (verify.json, verify.png, journal.sqlite, raw.h5, journal.jsonl, records/)")
    p.add_argument("--iteration", type=int, metavar="K", help="the compensator of iteration K (default: the last)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.campaign.compensator import kept_box, kept_controller, stored_procedure
    from setmem_hil.cli.commands.controller import implemented_guarantee
    from setmem_hil.io.target_file import load_target_procedure
    from setmem_hil.robust.controller_forms import second_order_sections
    from setmem_hil.verify import plan as vp

    target_procedure = load_target_procedure(args.procedure)
    t, v = target_procedure.target, target_procedure.verify
    record, K = kept_controller(args.run_dir, args.iteration, command="setmem-hil verify")
    guarantee = implemented_guarantee(args.run_dir, record, K, t.fs_hz, t.delay_samples, command="setmem-hil verify")  # exit 2 before anything moves
    model, calibration = kept_box(record)
    procedure = stored_procedure(args.run_dir)  # the structure (an emulated target's) and the weights
    weights = procedure.weights
    prewarp = float(record.mu_peak_omega)
    sos, sos_gain = second_order_sections(K, t.fs_hz, prewarp)
    frequencies = v.frequencies_rad_s or vp.chosen_frequencies(model, weights, K, t.fs_hz, t.delay_samples, prewarp, calibration)
    setup = vp.VerifySetup(model, calibration, weights, K, sos, sos_gain, prewarp, t.fs_hz, t.delay_samples, v.gains,
                           tuple(frequencies), v.injection_amplitude,
                           v.settle_s if v.settle_s is not None else vp.settle_time_s(model, K, v.gains[0]), v.periods,
                           full_gain_mu_bar=guarantee["implemented_mu_bar_certified"] or math.nan)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from setmem_hil.verify.session import run_verification

    result, failure = run_verification(setup, target_procedure, procedure, args.run_dir, out, quiet=args.quiet)
    from setmem_hil.io.verification_file import write_verification
    from setmem_hil.verify.document import verification_document

    doc = verification_document(result, setup, target_procedure, record)
    if result.points:
        from setmem_hil.verify.figure import write_figure

        write_figure(out / "verify.png", setup, result)
        doc["figure"] = str((out / "verify.png").resolve())
    write_verification(doc, out, args.run_dir)  # and the run's copy: its report shows the latest verification
    if failure is not None:
        raise failure
    first = result.first_outside
    if first is not None:
        m, (lo, hi) = first.measured, first.prediction.abs_range
        print(f"setmem-hil: verify: at {m.omega_rad_s:.6g} rad/s (gain {first.gain:g}) the measured |S| = {abs(m.S):.4g} "
              f"(+- {m.S_bound:.2g}) lies outside the predicted {lo:.4g}..{hi:.4g}"
              + _named(doc.get("discrepancy")), file=sys.stderr)
        return EXIT_OUTSIDE
    if not doc["verified"]:
        print(f"setmem-hil: verify: not verified: a gain step measured no point whose prediction could be contradicted "
              f"(|S| bounded within a factor of 10; {doc['uninformative_points']} uninformative point(s)): choose frequencies "
              "with informative predictions ([verify] frequencies_rad_s)", file=sys.stderr)
        return EXIT_OUTSIDE
    print(f"{out / 'verify.json'}: verified: {len(result.points)} points in {len(result.steps)} gain steps inside the prediction; "
          f"measured performance {doc['performance']['measured']:.4g} against the claimed {doc['performance']['claimed']:.4g}")
    return 0


def _named(discrepancy: dict | None) -> str:
    """``; the discrepancy names loop_gain (gain 1.296) at the plant's terminals (actuator or sensor)``."""
    if not discrepancy:
        return ""
    if discrepancy["effect"] == "unexplained":
        return "; the discrepancy names no effect (unexplained)"
    values = ", ".join(f"{k.replace('_', ' ')} {v:.4g}" for k, v in discrepancy["parameters"].items())
    where = {"compensator": "in the compensator's path", "plant_terminals": "at the plant's terminals"}.get(discrepancy.get("where"), "")
    side = f" ({discrepancy['side']})" if discrepancy.get("where") == "plant_terminals" and discrepancy.get("side") else ""
    if discrepancy.get("side") in ("actuator", "sensor"):
        side = f" (the {discrepancy['side']}'s side, told by the force channel)"
    return f"; the discrepancy names {discrepancy['effect']} ({values}) {where}{side}"

