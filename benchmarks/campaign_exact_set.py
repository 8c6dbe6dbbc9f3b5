"""Every campaign iteration's box against the exact feasible set of its own data (issue 62).

For each shipped 6.3.x procedure and seed, runs the campaign (``setmem-hil run``, the installed
command) and then, per iteration, holds each free parameter's interval against the extent of
points checked to fit every point within its recorded bound: SLSQP along every parameter both ways
from the iteration's witness (:func:`setmem_hil.identification.feasible_points.fitting_extent`,
another solver and formulation than the identification's conic programs). That extent is an
*inner* bound of the exact set's, so each ratio is an upper bound of the true one. Prints per
iteration the worst ratio per mode and overall, the witness's misfit, mu-bar, and per run the goal,
the experiments added and the rig time.

Usage::

    .venv/bin/python benchmarks/campaign_exact_set.py [--procedures fast,6.3.2,6.3.3,6.3.4] [--seeds 1,2,3]
        [--keep DIR] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PROCEDURES = {
    "fast": "procedures/beam_6_3_2_fast.toml",
    "6.3.2": "procedures/beam_6_3_2.toml",
    "6.3.3": "procedures/beam_6_3_3_snr10.toml",
    "6.3.4": "procedures/beam_6_3_4_resonance.toml",
}


def iteration_ratios(run_dir: Path) -> list[dict]:
    """Per iteration: the worst interval / inner-extent ratio per mode, the witness's misfit."""
    from setmem_hil.campaign.stored_run import open_run
    from setmem_hil.identification.feasible_points import fitting_extent
    from setmem_hil.identification.witness import find_witness
    from setmem_hil.model.frequency_data import FrequencyData

    run = open_run(run_dir)
    prior = run.procedure.prior.initial_bounds()
    rows = []
    for rec in run.iterations:
        data = FrequencyData.from_measurements(run.snapshot.measurements[: rec.n_points])
        lo, hi = np.asarray(rec.lower), np.asarray(rec.upper)
        w, g, E = data.omega_rad_s, data.response, data.bound
        witness = find_witness(w, g, E, lo, hi)
        row = {"k": rec.k, "points": rec.n_points, "mu": rec.mu_peak, "witness_misfit": witness.misfit}
        if witness.fits:
            in_lo, in_hi = fitting_extent(w, g, E, prior.lower, prior.upper, witness.x)
            free = hi > lo
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(free & (in_hi > in_lo), (hi - lo) / (in_hi - in_lo), np.nan)
            row["per_mode"] = [float(np.nanmax(r)) if np.isfinite(r).any() else None for r in ratio]
            row["worst"] = float(np.nanmax(ratio))
            row["outside"] = bool(np.any(in_lo < lo - 1e-12 * np.abs(lo)) or np.any(in_hi > hi + 1e-12 * np.abs(hi)))
        rows.append(row)
    return rows


def run_campaign(procedure: str, seed: int, out: Path) -> dict:
    t0 = time.perf_counter()
    done = subprocess.run([str(ROOT / ".venv/bin/setmem-hil"), "run", str(ROOT / procedure), "--out", str(out),
                           "--seed", str(seed), "--quiet"], capture_output=True, text=True)
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    return {"exit": done.returncode, "wall_s": time.perf_counter() - t0, "reached_goal": summary.get("reached_goal"),
            "experiments_added": summary.get("experiments_added"), "rig_s": summary.get("rig_s"),
            "final_mu": summary.get("final_mu_peak"), "compute_s": sum(summary.get("compute_s_per_iteration", []) or [0])
            if isinstance(summary.get("compute_s_per_iteration"), list) else summary.get("compute_s_per_iteration"),
            "stderr": done.stderr.strip().splitlines()[-1:] if done.returncode else []}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--procedures", default="fast,6.3.2")
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--keep", default=None, help="keep the run directories here")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="campaign-exact-"))
    results = []
    for name in args.procedures.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            out = base / f"{name}-seed{seed}"
            if out.exists():
                campaign = {"exit": None, "note": "reused"}
            else:
                campaign = run_campaign(PROCEDURES[name], seed, out)
            rows = iteration_ratios(out)
            results.append({"procedure": name, "seed": seed, "campaign": campaign, "iterations": rows})
            print(f"{name} seed {seed}: exit {campaign.get('exit')}, goal {campaign.get('reached_goal')}, added "
                  f"{campaign.get('experiments_added')}, rig {campaign.get('rig_s') or 0:.0f} s, final mu-bar "
                  f"{campaign.get('final_mu') or float('nan'):.4f}, wall {campaign.get('wall_s') or 0:.0f} s", flush=True)
            for row in rows:
                modes = " / ".join("-" if r is None else f"{r:.2f}" for r in row.get("per_mode", []))
                print(f"  it {row['k']:2d} ({row['points']:3d} pts) mu-bar {row['mu']:.4f} witness {row['witness_misfit']:.3f} "
                      f"worst {row.get('worst', float('nan')):.3f} [{modes}]" + ("  A FITTING POINT OUTSIDE" if row.get("outside") else ""),
                      flush=True)
    worst = max((r.get("worst", 0.0) for res in results for r in res["iterations"]), default=float("nan"))
    print(f"worst ratio over every iteration: {worst:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
