"""``setmem-hil validate RUN_DIR [--samples N] [--out REPORT.json] [--fs HZ]``: is the claim true?

Checks the compensator a run kept (:mod:`setmem_hil.campaign.compensator`) plant by plant with
the exact robust-performance test of one plant (:mod:`setmem_hil.robust.validation`):

* the **truth**, where the backend simulates one (sim, time-domain, loopback, emulated
  instruments; all its modes): nominal closed-loop stability and the peak of
  ``|W2 S| + |W1 K S|``;
* the **interval set**: every vertex of the final parameter box (up to 2^12, else a Latin
  hypercube of 4096) plus ``--samples`` random points; any plant unstable or with a peak >= 1
  while mu-bar < 1 was claimed falsifies the claim (exit 3, naming the plant and frequency).
  Where the iteration holds a common gain (``common_gain``: sampled sensors' calibration, one
  scale on the whole plant) the set is the box as measured times that gain: every plant drawn
  from that box, at each end of the gain interval;
* a **closed-loop simulation** of the truth under the discrete compensator (Tustin at ``--fs``,
  prewarped at the mu-bar peak), a sinusoidal disturbance at the performance input at the truth's
  peak frequency: the measured weighted performance against the frequency-domain value.

REPORT.json keys: ``truth`` (``stable``, ``rp_peak``, ``rp_peak_omega``; null without a truth),
``samples`` (``n``, ``worst_rp_peak``, ``worst_omega``, ``violations``, ``drawn``,
``worst_plant``), ``closed_loop_sim`` (null without a truth), ``claimed_mu_peak``, ``iteration``, ``design``,
``figure``, ``implemented`` (with ``--fs F --delay-samples D``: the loop as a real-time target runs
it, as ``controller --delay-samples`` reports it; null without). The figure (``validate.png`` beside the report) shows ``|W2 S|`` and ``|W1 K S|`` of the
truth and of the worst sampled plant against 1.

Exit codes: 0 no checked plant violates the claim; 3 one does; 2 bad arguments, no iteration, or
(with ``--delay-samples``) an implemented loop whose certified mu-bar is not below 1.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

EXIT_FALSIFIED = 3


def _claimed_set(record, samples: int):
    """The plants the iteration's mu-bar claim covers (module docstring): its interval box, or
    with a common gain the box as measured times each end of the gain."""
    from setmem_hil.model.modal_model import B0, B1, IntervalModel
    from setmem_hil.robust.validation import box_plants

    if record.common_gain is None:
        return box_plants(IntervalModel(record.lower, record.upper), samples, seed=record.k)
    measured = IntervalModel(np.array(record.common_gain["lower"]), np.array(record.common_gain["upper"]))
    base, drawn = box_plants(measured, samples, seed=record.k)
    plants = []
    for k in record.common_gain["gain"]:
        scaled = base.copy()
        scaled[:, :, [B1, B0]] *= float(k)
        plants.append(scaled)
    return np.concatenate(plants), f"{drawn} x {len(record.common_gain['gain'])} gains"


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "validate",
        help="check the compensator a run kept against the truth and plants sampled from the interval box",
        description="Check the robust-performance claim of a run's last compensator plant by plant: the simulated truth "
        "(where there is one), every vertex of the parameter box plus random plants, and a closed-loop simulation. "
        "Exit 0 when no checked plant violates the claim, 3 when one does.",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="run directory (holds journal.sqlite)")
    p.add_argument("--samples", type=int, default=1000, metavar="N", help="random plants besides the box's vertices (default 1000)")
    p.add_argument("--out", metavar="REPORT.json", help="report file (default RUN_DIR/validate.json)")
    p.add_argument("--fs", type=float, metavar="HZ", help="sample rate of the closed-loop simulation (default: 20 samples "
                   "per period of the fastest simulated mode, at least 20 per period of the peak)")
    p.add_argument("--delay-samples", type=int, metavar="D", help="with --fs: also analyse the loop as a real-time target runs "
                   "it (the sections, D samples of delay, the hold): implemented_mu_bar in the report; exit 2 when its certified value is not below 1, "
                   "naming the sample rate needed")
    p.add_argument("--iteration", type=int, metavar="K", help="the compensator of iteration K (default: the last)")
    p.set_defaults(func=run)


def _band(record) -> np.ndarray:
    """The analysis band, densely: 4000 log-spaced points over the stored grid's range."""
    omega = np.asarray(record.omega, dtype=float)
    lo, hi = float(np.min(omega[omega > 0])), float(np.max(omega))
    return np.geomspace(lo, hi, 4000)


def _controller_on(K, grid):
    from setmem_hil.robust.controller_forms import frequency_response

    return frequency_response(K, grid)


def _certified_truth_peak(truth, K, weights) -> dict:
    """The truth's peak certified on the whole band (issue 27, item 3): for one plant the two
    complex blocks make mu-bar exact, ``|W2 S| + |W1 K S|``, so the band certificate of the
    analysis proves the one-plant test between grid points too."""
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.robust.analysis import analyze_robust_performance

    result = analyze_robust_performance(IntervalModel.point(truth), weights, controller=K)
    return {"rp_peak_certified": float(result.mu_peak), "rp_certified_omega": float(result.mu_peak_omega),
            "rp_certified": bool(result.mu_peak_certified), "rp_certified_intervals": int(result.mu_certified_intervals)}


def run(args: argparse.Namespace) -> int:
    from setmem_hil.campaign.compensator import kept_controller
    from setmem_hil.errors import InputFormatError
    from setmem_hil.experiment_factory import true_structure
    from setmem_hil.io.atomic_file import write_json_atomic
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import parse_procedure_text
    from setmem_hil.robust.validation import closed_loop_simulation

    if args.samples < 0:
        raise InputFormatError("setmem-hil validate", "arguments", f"--samples {args.samples}: expected >= 0")
    if args.delay_samples is not None and (args.fs is None or args.delay_samples < 0):
        raise InputFormatError("setmem-hil validate", "arguments", f"--delay-samples {args.delay_samples}: needs --fs and a count >= 0")
    record, K = kept_controller(args.run_dir, args.iteration, command="setmem-hil validate")
    implemented = None
    if args.delay_samples is not None:  # before the long checks: a rate that loses the margin is bad input
        from setmem_hil.cli.commands.controller import implemented_guarantee

        implemented = implemented_guarantee(args.run_dir, record, K, args.fs, args.delay_samples, command="setmem-hil validate")
    with Journal.open(args.run_dir) as j:
        procedure = parse_procedure_text(j.run_info()["procedure_text"], f"{args.run_dir} (stored procedure)")
    weights = procedure.weights
    grid = _band(record)
    k_grid = _controller_on(K, grid)
    claimed = float(record.mu_peak)

    truth = true_structure(procedure)
    truth_doc = None if truth is None else _truth_check(truth, K, weights, grid, k_grid)
    plants, drawn = _claimed_set(record, args.samples)
    worst, violations = _sampled_check(plants, K, weights, grid, k_grid, claimed)
    samples_doc = {"n": int(len(plants)), "drawn": f"{drawn} + {args.samples} random", "worst_rp_peak": float(worst[0]),
                   "worst_omega": float(worst[1]), "violations": len(violations),
                   "worst_plant": None if worst[2] is None else np.asarray(worst[2]).tolist()}

    sim_doc = None
    if truth is not None and truth_doc["stable"]:
        from setmem_hil.robust.controller_forms import tustin_prewarped

        fastest = float(np.max(truth.natural_frequencies))
        fs = args.fs or max(20 * fastest, 20 * truth_doc["rp_peak_omega"]) / (2 * math.pi)
        discrete = tustin_prewarped(K, fs, float(record.mu_peak_omega)) if record.mu_peak_omega < math.pi * fs \
            else tustin_prewarped(K, fs, truth_doc["rp_peak_omega"])
        sim_doc = closed_loop_simulation(truth, K, discrete, weights, truth_doc["rp_peak_omega"])

    out = Path(args.out) if args.out else Path(args.run_dir) / "validate.json"
    figure = out.with_suffix(".png")
    _figure(figure, truth, plants, worst[2], K, weights, grid, k_grid)
    design = record.design or "h2"
    doc = {"iteration": int(record.k), "claimed_mu_peak": claimed, "design": design, "truth": truth_doc, "samples": samples_doc,
           "closed_loop_sim": sim_doc, "figure": str(figure), "implemented": implemented}
    write_json_atomic(doc, out)
    print(f"{out}: iteration {record.k} ({design} design), claimed mu-bar {claimed:.4g}; "
          + (f"truth {'stable' if truth_doc['stable'] else 'UNSTABLE'}, peak {truth_doc['rp_peak']:.4g} at "
             f"{truth_doc['rp_peak_omega']:.4g} rad/s; " if truth_doc else "no simulated truth; ")
          + f"{len(plants)} plants ({drawn}), worst peak {worst[0]:.4g} at {worst[1]:.4g} rad/s, {len(violations)} violations")
    falsified = violations or (truth_doc is not None and claimed < 1.0 and (not truth_doc["stable"] or truth_doc["rp_peak"] >= 1.0))
    if falsified:
        _say_falsified(claimed, violations, truth_doc)
        return EXIT_FALSIFIED
    return 0


def _truth_check(truth, K, weights, grid, k_grid) -> dict:
    """The simulated truth's closed loop: stable?, its peak of ``|W2 S| + |W1 K S|`` (certified on the band)."""
    from setmem_hil.robust.validation import closed_loop_stable, rp_peak

    peak, where = rp_peak(truth, K, weights, grid, k_grid)
    doc = {"stable": closed_loop_stable(truth, K), "rp_peak": peak, "rp_peak_omega": where, "modes": int(truth.n_modes)}
    if doc["stable"]:
        doc.update(_certified_truth_peak(truth, K, weights))
        if doc["rp_peak_certified"] > peak:  # the certificate found more than the dense grid: report that
            doc["rp_peak"], doc["rp_peak_omega"] = doc["rp_peak_certified"], doc["rp_certified_omega"]
    return doc


def _sampled_check(plants, K, weights, grid, k_grid, claimed: float):
    """Every sampled plant of the box: the worst ``(peak, omega, plant)`` and the plants that
    falsify a claimed mu-bar < 1 (unstable, or a peak >= 1)."""
    from setmem_hil.model.modal_model import ModalParameters
    from setmem_hil.robust.validation import closed_loop_stable, rp_peak

    worst = (-math.inf, math.nan, None)
    violations = []
    for values in plants:
        plant = ModalParameters(values)
        stable = closed_loop_stable(plant, K)
        peak, where = rp_peak(plant, K, weights, grid, k_grid, refine=1) if stable else (math.inf, math.nan)
        if peak > worst[0]:
            worst = (peak, where, values)
        if claimed < 1.0 and (not stable or peak >= 1.0):
            violations.append((values, peak, where, stable))
    return worst, violations


def _say_falsified(claimed: float, violations: list, truth_doc: dict | None) -> None:
    import sys

    if violations:
        values, peak, where, stable = max(violations, key=lambda v: v[1])
        plant = "; ".join(f"mode {i + 1}: a1 {v[0]:.6g}, a0 {v[1]:.6g}, b1 {v[2]:.6g}, b0 {v[3]:.6g}" for i, v in enumerate(values))
        what = "an unstable closed loop" if not stable else f"|W2 S| + |W1 K S| = {peak:.4g} at {where:.6g} rad/s"
        print(f"setmem-hil: claim falsified: mu-bar {claimed:.4g} < 1 was claimed, but the plant ({plant}) in the interval box "
              f"gives {what}", file=sys.stderr)
    else:
        what = "an unstable closed loop" if not truth_doc["stable"] else \
            f"|W2 S| + |W1 K S| = {truth_doc['rp_peak']:.4g} at {truth_doc['rp_peak_omega']:.6g} rad/s"
        print(f"setmem-hil: claim falsified: mu-bar {claimed:.4g} < 1 was claimed, but the true structure gives {what}", file=sys.stderr)


def _figure(path: Path, truth, plants, worst, K, weights, grid, k_grid) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from setmem_hil.model.modal_model import ModalParameters

    s = 1j * grid
    w1 = np.polyval(weights.w1_num, s) / np.polyval(weights.w1_den, s)
    w2_num, w2_den = weights.w2_for_design()
    w2 = np.polyval(w2_num, s) / np.polyval(w2_den, s)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, params, style in (("truth", truth, "-"), ("worst sampled plant", None if worst is None else ModalParameters(worst), "--")):
        if params is None:
            continue
        sens = 1.0 / (1.0 - np.ravel(params.frequency_response(grid)) * k_grid)
        ax.loglog(grid, np.abs(w2 * sens), style, color="C0", label=f"|W2 S|, {label}")
        ax.loglog(grid, np.abs(w1 * k_grid * sens), style, color="C1", label=f"|W1 K S|, {label}")
        ax.loglog(grid, np.abs(w2 * sens) + np.abs(w1 * k_grid * sens), style, color="C3", label=f"sum, {label}")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xlabel("frequency (rad/s)")
    ax.set_ylabel("magnitude")
    ax.set_title("robust performance plant by plant: |W2 S| + |W1 K S| < 1")
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
