"""Confusion table of the discrepancy workflow on beam data with hidden effects (issue 6).

Usage::

    .venv/bin/python benchmarks/discrepancy_confusion.py [--per-effect 24] [--clean 24] [--seed0 50000]
        [--jobs 1] [--lean] [--json OUT.json]

Each case: :func:`setmem_hil.sim_backends.hidden_effects.draw_hidden_effect_case` (three-mode
beam, the effect hidden at a random strength, random noise level and seed; see that module for
the ranges and the detectability rule), then
:func:`setmem_hil.discrepancy.workflow.discrepancy_from_prior` with the thesis's three-mode prior
(default settings: bound inflation factor and effect intervals included; ``--lean`` skips both).
Prints the confusion table (true effect x named effect), the rates the issue asks for, the
after-figures, timing, and the before/after figures of one case of each kind.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor

NAMES = ("none", "time_delay", "first_order_lag", "feedthrough", "extra_mode", "unexplained")


def run_case(args):
    effect, seed, lean, margin = args
    from setmem_hil.discrepancy.workflow import DiscrepancySettings, discrepancy_from_prior
    from setmem_hil.io.procedure import thesis_beam_prior
    from setmem_hil.sim_backends.hidden_effects import draw_hidden_effect_case

    case = draw_hidden_effect_case(effect, seed, detectable_margin=margin)
    settings = DiscrepancySettings(inflation_steps=0, interval_steps=0) if lean else DiscrepancySettings()
    t0 = time.perf_counter()
    report = discrepancy_from_prior(case.data, thesis_beam_prior(), settings)
    dt = time.perf_counter() - t0
    doc = report.to_document()
    return {
        "effect": effect, "seed": seed, "true_params": case.params, "noise_scale": case.noise_scale,
        "margin": case.margin, "redraws": case.redraws, "named": report.decision, "seconds": dt,
        "before": doc["before"], "after": doc["after"], "effects": doc["effects"],
        "n_bands": len(doc["disagreement_bands"]),
    }


def _figure(r: dict, lean: bool, margin: float, directory: str) -> None:
    """Re-run one case (deterministic from its seed) and plot it."""
    from pathlib import Path

    from setmem_hil.discrepancy.workflow import DiscrepancySettings, discrepancy_from_prior
    from setmem_hil.discrepancy.plot import plot_discrepancy
    from setmem_hil.io.procedure import thesis_beam_prior
    from setmem_hil.sim_backends.hidden_effects import draw_hidden_effect_case

    case = draw_hidden_effect_case(r["effect"], r["seed"], detectable_margin=margin)
    settings = DiscrepancySettings(inflation_steps=0, interval_steps=0) if lean else DiscrepancySettings()
    report = discrepancy_from_prior(case.data, thesis_beam_prior(), settings)
    Path(directory).mkdir(parents=True, exist_ok=True)
    path = Path(directory) / f"discrepancy_{r['effect']}_{r['seed']}.png"
    plot_discrepancy(report, path, title=f"hidden {r['effect']} (seed {r['seed']}): named {report.decision}")
    print(f"  {'':16s} figure: {path}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-effect", type=int, default=24, help="hidden cases per effect")
    ap.add_argument("--clean", type=int, default=24, help="clean cases")
    ap.add_argument("--seed0", type=int, default=50000)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--lean", action="store_true", help="skip the inflation factor and effect intervals")
    ap.add_argument("--json", help="write every case's outcome here")
    ap.add_argument("--figures", metavar="DIR", help="write the plot of the one case of each kind shown here")
    ap.add_argument("--margin", type=float, default=None,
                    help="detectability margin of the generator (default: its DETECTABLE_MARGIN, 2)")
    a = ap.parse_args(argv)
    from setmem_hil.sim_backends.hidden_effects import DETECTABLE_MARGIN, HIDDEN_EFFECTS

    margin = DETECTABLE_MARGIN if a.margin is None else a.margin

    jobs = []
    for k, effect in enumerate(HIDDEN_EFFECTS):
        n = a.clean if effect == "none" else a.per_effect
        jobs += [(effect, a.seed0 + 10000 * k + i, a.lean, margin) for i in range(n)]
    t0 = time.perf_counter()
    if a.jobs > 1:
        with ProcessPoolExecutor(a.jobs) as pool:
            results = list(pool.map(run_case, jobs))
    else:
        results = [run_case(j) for j in jobs]
    wall = time.perf_counter() - t0

    table = {t: {n: 0 for n in NAMES} for t in HIDDEN_EFFECTS}
    for r in results:
        table[r["effect"]][r["named"]] += 1
    width = max(len(n) for n in NAMES) + 2
    print(f"confusion table ({len(results)} cases, detectability margin {margin:g}; rows: true effect, columns: named effect)")
    print("true \\ named".ljust(18) + "".join(n.rjust(width) for n in NAMES))
    for t in HIDDEN_EFFECTS:
        print(t.ljust(18) + "".join(str(table[t][n]).rjust(width) for n in NAMES))
    hidden = [r for r in results if r["effect"] != "none"]
    clean = [r for r in results if r["effect"] == "none"]
    right = [r for r in hidden if r["named"] == r["effect"]]
    print(f"\nhidden cases named right: {len(right)}/{len(hidden)} = {len(right) / max(len(hidden), 1):.1%} (contract >= 90%)")
    none_ok = sum(r["named"] == "none" for r in clean)
    print(f"clean cases answered none: {none_ok}/{len(clean)} = {none_ok / max(len(clean), 1):.1%} (contract >= 95%)")
    after_max = max((r["after"]["max_normalized_residual"] for r in right), default=float("nan"))
    feasible = sum(bool(r["after"]["feasible"]) for r in right)
    print(f"named right: worst after-residual {after_max:.3f} (contract <= 1.05), after feasible {feasible}/{len(right)}")
    secs = sorted(r["seconds"] for r in results)
    print(f"workflow time per case: median {secs[len(secs) // 2]:.2f} s, max {secs[-1]:.2f} s; wall {wall:.0f} s")
    covered = total = 0
    for r in right:
        params = r["effects"][0]["params"]
        for key, value in r["true_params"].items():
            if f"{key}_interval" in params:
                lo, hi = params[f"{key}_interval"]
                total += 1
                covered += lo <= value <= hi
    if total:
        print(f"effect-parameter intervals containing the true value: {covered}/{total}")
    redraws = sum(r["redraws"] for r in hidden)
    print(f"strength draws rejected by the detectability rule: {redraws} (over {len(hidden)} hidden cases)")
    print("\nbefore/after, one case of each kind:")
    for t in HIDDEN_EFFECTS:
        r = next((r for r in results if r["effect"] == t and r["named"] == t), None) or next(
            (r for r in results if r["effect"] == t), None)
        if r is None:
            continue
        b, f = r["before"], r["after"]
        eff = r["effects"][0] if r["effects"] else {"name": "none", "params": {}}
        params = {k: (round(v, 5) if isinstance(v, float) else [round(x, 5) for x in v]) for k, v in eff["params"].items()}
        truep = {k: round(v, 5) for k, v in r["true_params"].items()}
        print(f"  {t:16s} seed {r['seed']}: true {truep}; named {eff['name']} {params}")
        print(f"  {'':16s} before: max rho {b['max_normalized_residual']:.3g}, feasible {b['feasible']}, "
              f"inflation x{b.get('bound_inflation_factor', float('nan')) or float('nan'):.3g}; "
              f"after: max rho {f['max_normalized_residual']:.3g}, feasible {f['feasible']}")
        if a.figures:
            _figure(r, lean=a.lean, margin=margin, directory=a.figures)
    misses = [r for r in results if r["named"] != r["effect"]]
    if misses:
        print("\nmisses:")
        for r in misses:
            print(f"  {r['effect']} seed {r['seed']} named {r['named']}: true {r['true_params']}, margin {r['margin']:.2f}, "
                  f"before {r['before']['max_normalized_residual']:.3g}")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
