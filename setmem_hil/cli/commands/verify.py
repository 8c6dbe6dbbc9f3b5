"""``setmem-hil verify RUN_DIR --procedure TARGET.toml --out DIR``: the compensator on the rig.

Loads the compensator a run kept into the real-time target of TARGET.toml (``[target]``:
:mod:`setmem_hil.io.target_file`), engages it in steps of gain, each certified before it is
engaged (the implemented mu-bar with the target's sections, delay and hold), measures the closed
loop by injecting sines at the summing junction, and checks every point against the box's
guaranteed prediction (:mod:`setmem_hil.verify.plan`, a plan on the run engine).

Output: ``DIR/verify.json`` (``verified``, ``target``, ``implemented_mu_bar``, ``steps[]`` with
their ``points[]``, ``performance``, ``first_outside``, ``discrepancy``, ``figure``; also copied
to ``RUN_DIR/verify.json``, which the run's report shows), ``DIR/verify.png`` (the
predicted band of ``|S|`` and the measured points), ``DIR/journal.jsonl`` (every document, one
JSON line each, flushed as written) and ``DIR/records/`` (each point's injection, drive and
response, ``<seq>.npz``; the rig at rest before engaging, ``baseline.npz``).

Exit codes: 0 every point inside its prediction; 3 a point outside (named); 4 a target or
instrument fault, or a loop that grew or did not settle (the target bypassed and the generator off, confirmed);
2 bad input, or a loop whose certified implemented mu-bar is not below 1 (never engaged; the sample rate needed
is named); 130 interrupted (bypassed, confirmed).
"""

from __future__ import annotations

import argparse
import json
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
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (verify.json, verify.png, journal.jsonl, records/)")
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
    doc = _document(result, setup, target_procedure, record)
    from setmem_hil.io.atomic_file import write_json_atomic

    if result.points:
        from setmem_hil.verify.figure import write_figure

        write_figure(out / "verify.png", setup, result)
        doc["figure"] = str((out / "verify.png").resolve())
    write_json_atomic(doc, out / "verify.json")
    write_json_atomic(doc, Path(args.run_dir) / "verify.json")  # the run's report shows the latest verification
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


def _document(result, setup, target_procedure, record) -> dict:
    from setmem_hil.verify.closed_loop_discrepancy import closed_loop_discrepancy

    identity = result.identity
    # the performance is claimed for the full gain only (a fraction of it rejects less)
    measured = max((p.weighted_performance for p in result.points if p.gain >= 1.0), default=None)
    first = result.first_outside
    doc = {
        "verified": bool(result.points) and first is None and len(result.steps) == len(setup.gains) and result.informative_in_every_step(),
        "uninformative_points": sum(not p.informative for p in result.points),
        "iteration": int(record.k),
        "target": {"kind": target_procedure.target.kind, "identity": None if identity is None else identity.text,
                   "fs_hz": setup.fs_hz, "delay_samples": setup.delay_samples,
                   "checksum_read_back": None if result.checksum is None else f"{result.checksum:08X}"},
        "implemented_mu_bar": None if not math.isfinite(result.implemented_mu_bar) else result.implemented_mu_bar,
        "continuous_mu_bar": float(record.mu_peak),
        "baseline_response_rms": None if not math.isfinite(result.baseline_rms) else result.baseline_rms,
        "steps": result.steps,
        "performance": {"measured": measured, "claimed": None if not math.isfinite(result.implemented_mu_bar) else result.implemented_mu_bar},
        "first_outside": None if first is None else first.to_document() | {"gain": first.gain},
        "discrepancy": None,
    }
    if first is not None:
        doc["discrepancy"] = closed_loop_discrepancy(result.points, setup)
    return json.loads(json.dumps(doc, default=float))


def _named(discrepancy: dict | None) -> str:
    """``; the discrepancy names loop_gain (gain 1.296) at the plant's terminals (actuator or sensor)``."""
    if not discrepancy:
        return ""
    if discrepancy["effect"] == "unexplained":
        return "; the discrepancy names no effect (unexplained)"
    values = ", ".join(f"{k.replace('_', ' ')} {v:.4g}" for k, v in discrepancy["parameters"].items())
    where = {"compensator": "in the compensator's path", "plant_terminals": "at the plant's terminals"}.get(discrepancy.get("where"), "")
    side = f" ({discrepancy['side']})" if discrepancy.get("where") == "plant_terminals" and discrepancy.get("side") else ""
    return f"; the discrepancy names {discrepancy['effect']} ({values}) {where}{side}"

