"""The robust design against the thesis's H2 loop on the section 6.3.2 campaign (issue 38).

For each seed and each design (``h2``: the thesis; ``h2-floor``: the H2 loop whose input design
ranks the candidates that remove a floor first; ``robust``: the compensator tuned to the
mixed-mu bound, the default, with that input design) runs the shipped 6.3.2 procedure on the simulated beam and prints
the experiments added to reach mu-bar < 1, the final mu-bar, the rig time, the compute time of
the campaign and its largest ratio of an iteration's compute to the rig time of the experiment
it chose, and whether the final compensator holds for the true beam and for sampled plants of its
box (the check of ``setmem-hil validate``). Medians over the seeds close the table; ``--figure``
draws experiments-to-goal and final mu-bar per seed, H2 against robust.

With ``--procedures`` it runs each listed procedure once with the robust design (and ``--design``
to choose) and prints the same per-iteration compute ratio: the issue's "a tenth of the rig time
of the experiment that follows, on every shipped procedure".

Usage::

    .venv/bin/python benchmarks/robust_design.py --seeds 1-10 --workers 2 [--figure docs/images/robust-design.png]
    .venv/bin/python benchmarks/robust_design.py --procedures procedures/beam_6_3_2_fast.toml,procedures/beam_6_3_2_50hz.toml

Runs are independent processes (``--workers``), BLAS pinned to one thread each; the robust
design's own two threads run inside each process.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DESIGNS = ("h2", "h2-floor", "robust")  # h2-floor: the H2 loop with the floor-aware input design


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = (int(v) for v in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(v) for v in text.split(",")]


def _compute_ratio(doc: dict) -> float:
    """Largest compute time of an iteration over the rig time of the dwells it chose."""
    ratios = [it["compute_s"] / it["rig_s"] for it in doc["iterations"] if it.get("next_omega") is not None and it.get("rig_s")]
    return max(ratios, default=0.0)


def _validate(doc_controller, record, weights, truth, n_samples: int = 300) -> dict:
    """The final compensator on the truth and on plants of its box (as ``setmem-hil validate``)."""
    import numpy as np

    from setmem_hil.model.modal_model import IntervalModel, ModalParameters
    from setmem_hil.robust.validation import box_plants, closed_loop_stable, rp_peak

    grid = np.geomspace(0.1, 1000.0, 800)
    truth_ok = closed_loop_stable(truth, doc_controller) and rp_peak(truth, doc_controller, weights, grid)[0] < 1.0
    plants, _ = box_plants(IntervalModel(record.lower, record.upper), n_samples, seed=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(plants.shape[0], size=min(n_samples, plants.shape[0]), replace=False)
    worst = 0.0
    for values in plants[pick]:
        plant = ModalParameters(values)
        if not closed_loop_stable(plant, doc_controller):
            return {"truth": bool(truth_ok), "box": False, "box_worst": float("inf")}
        worst = max(worst, rp_peak(plant, doc_controller, weights, grid)[0])
    return {"truth": bool(truth_ok), "box": bool(worst < 1.0), "box_worst": worst}


def run_one(design: str, seed: int, procedure_path: str | None = None, validate: bool = True) -> dict:
    """One campaign into a temporary journal; its summary plus timing and validation."""
    import tempfile

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.robust.controller_forms import StateSpace
    from setmem_hil.sim_backends.beam import beam_parameters

    proc = load_procedure(procedure_path or REPO / "procedures" / "beam_6_3_2.toml")
    if procedure_path is None:
        proc = dataclasses.replace(proc, seed=seed)
    with tempfile.TemporaryDirectory() as tmp:
        journal = Journal.create(Path(tmp) / "journal.sqlite", procedure_text=proc.source_text, procedure_name=proc.name,
                                 seed=proc.seed, software_version="bench", backend=proc.backend.kind, strategy="mu",
                                 design=design.split("-")[0])
        t0 = time.perf_counter()
        with open_experiment(proc, proc.seed) as experiment:
            summary = run_campaign(proc, experiment, journal, seed=proc.seed, design=design.split("-")[0],
                                   floor_aware=True if design == "h2-floor" else None)
        wall = time.perf_counter() - t0
        record = journal.iterations()[-1]
        journal.close()
    doc = summary.to_document()
    doc.update(design=design, seed=proc.seed, wall_s=wall, compute_total_s=sum(it["compute_s"] for it in doc["iterations"]),
               compute_ratio=_compute_ratio(doc), procedure=str(procedure_path or "beam_6_3_2.toml"))
    if validate and record.controller is not None and proc.backend.kind == "sim":
        K = StateSpace.from_lists(record.controller)
        truth = beam_parameters().truncated(proc.prior.n_modes) if proc.backend.simulation.first_mode_rad_s == 1.0 else None
        if truth is not None:
            doc["validate"] = _validate(K, record, proc.weights, truth)
    return doc


def _median(values):
    return statistics.median(values) if values else float("nan")


def _print_seed_table(docs: list[dict]) -> None:
    print(f"{'seed':>4} {'design':>7} {'added':>5} {'final mu':>9} {'rig s':>7} {'compute s':>9} {'max c/rig':>9} {'truth':>5} {'box':>5}")
    for d in sorted(docs, key=lambda d: (d["seed"], d["design"])):
        v = d.get("validate", {})
        added = str(d["experiments_added"]) if d["reached_goal"] else f">{d['max_experiments']}"
        print(f"{d['seed']:>4} {d['design']:>7} {added:>5} {d['final_mu_peak']:>9.4f} {d['rig_s']:>7.0f} {d['compute_total_s']:>9.1f} "
              f"{d['compute_ratio']:>9.4f} {str(v.get('truth', '-')):>5} {str(v.get('box', '-')):>5}")
    for design in DESIGNS:
        mine = [d for d in docs if d["design"] == design]
        if not mine:
            continue
        print(f"median {design:>6}: added {_median([d['experiments_added'] for d in mine])}, final mu-bar "
              f"{_median([d['final_mu_peak'] for d in mine]):.4f}, rig {_median([d['rig_s'] for d in mine]):.0f} s, compute "
              f"{_median([d['compute_total_s'] for d in mine]):.1f} s (max {max(d['compute_total_s'] for d in mine):.1f} s), "
              f"compute/rig {max(d['compute_total_s'] / d['rig_s'] for d in mine):.4f} at most, reached "
              f"{sum(d['reached_goal'] for d in mine)}/{len(mine)}")


def _figure(docs: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for design, marker, colour in (("h2", "o", "tab:grey"), ("h2-floor", "^", "tab:orange"), ("robust", "s", "tab:blue")):
        mine = sorted((d for d in docs if d["design"] == design), key=lambda d: d["seed"])
        seeds = [d["seed"] for d in mine]
        if not mine:
            continue
        ax1.plot(seeds, [d["experiments_added"] for d in mine], marker=marker, color=colour, linestyle="none", label=design)
        ax2.plot(seeds, [d["final_mu_peak"] for d in mine], marker=marker, color=colour, linestyle="none", label=design)
    ax1.set_xlabel("seed")
    ax1.set_ylabel("experiments added to reach mu-bar < 1")
    ax1.yaxis.get_major_locator().set_params(integer=True)
    ax1.xaxis.get_major_locator().set_params(integer=True)
    ax2.axhline(1.0, color="k", linewidth=0.8)
    ax2.set_xlabel("seed")
    ax2.set_ylabel("final mu-bar (certified)")
    ax2.xaxis.get_major_locator().set_params(integer=True)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("Section 6.3.2 campaign on the simulated beam: H2 against the robust design")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1-10", help="seeds, e.g. 1-10 or 1,4,7")
    ap.add_argument("--designs", default="h2,robust")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--procedures", help="comma-separated procedure files: one run each (their own seed)")
    ap.add_argument("--figure", help="write the seeds figure here (PNG)")
    ap.add_argument("--json", help="write every run's document here")
    args = ap.parse_args(argv)
    designs = [d for d in args.designs.split(",") if d]
    if args.procedures:
        jobs = [(design, 0, p, False) for p in args.procedures.split(",") for design in designs]
    else:
        jobs = [(design, seed, None, True) for seed in _seeds(args.seeds) for design in designs]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        docs = list(pool.map(run_one, *zip(*jobs)))
    if args.procedures:
        for d in docs:
            print(f"{d['procedure']}: {d['design']}, reached {d['reached_goal']}, final mu-bar {d['final_mu_peak']:.4f}, "
                  f"{d['experiments_added']} added, rig {d['rig_s']:.0f} s, compute {d['compute_total_s']:.1f} s, "
                  f"largest iteration compute / rig of its experiment {d['compute_ratio']:.4f}")
    else:
        _print_seed_table(docs)
    if args.figure:
        _figure(docs, args.figure)
    if args.json:
        Path(args.json).write_text(json.dumps(docs, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
