"""Benchmark: closely spaced modes against the exact feasible set (issue 47).

For each separation of the pair (10, 3, 1 and 0.5 %), residue signs (opposite: 4 and -2.5; same:
4 and 2.5) and noise level (the bound 2 % |G| + 1e-4, and five times it), on the synthetic
structure of :mod:`setmem_hil.sim_backends.close_pair` (300 lines), identifies the model and
prints, per mode, each interval's width over the exact feasible set's extent. The exact set is
computed independently of the identification: the model linearised at the truth, each point's
disc as an inscribed 64-gon, every extent a linear program in HiGHS
(:func:`setmem_hil.identification.exact_set.linearised_extent`). Also printed: whether the truth is
inside every interval, whether every mode is verified, the groups, and the time. Last, the time
of 1,200 lines with the 3 % pair.

Run: ``.venv/bin/python benchmarks/close_modes.py [--separations 0.1,0.03] [--lines 300]
[--figure docs/images/close-modes-ratios.png]``; ``--figure`` also draws each case's worst ratio
against the separation (the figure in docs/closely-spaced-modes.md).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from setmem_hil.identification.algorithm import IdentifySettings, identify
from setmem_hil.identification.exact_set import linearised_extent
from setmem_hil.sim_backends.close_pair import close_pair_case


def one_case(separation, residues, noise, lines, groups=True):
    truth, data, prior = close_pair_case(separation, residues, noise, lines)
    start = time.perf_counter()
    result = identify(data, prior, settings=IdentifySettings(groups=groups))
    elapsed = time.perf_counter() - start
    box = prior.initial_bounds()
    ex_lo, ex_hi = linearised_extent(data.omega_rad_s, data.response, data.bound, truth.values, box.lower, box.upper)
    ratio = result.model.width / (ex_hi - ex_lo)
    return result, ratio, bool(result.model.contains(truth).all()), elapsed


def ratio_figure(rows, path) -> None:
    """Each case's worst interval/exact ratio against the separation; ``rows`` are
    ``(separation, residues, noise, worst ratio)``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for residues, marker in (("opposite", "o"), ("same", "s")):
        for noise, colour in ((1.0, "tab:blue"), (5.0, "tab:red")):
            pts = sorted((sep, r) for sep, res, nz, r in rows if res == residues and nz == noise)
            if pts:
                ax.plot([100 * p[0] for p in pts], [p[1] for p in pts], marker=marker, color=colour,
                        label=f"{residues} residues, noise {noise:g}x")
    ax.axhline(1.5, color="k", linestyle="--", linewidth=1, label="target 1.5")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("separation of the pair (%)")
    ax.set_ylabel("worst interval / exact set")
    ax.set_title("Close pairs: widest interval over the exact set (300 lines)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--separations", default="0.1,0.03,0.01,0.005")
    parser.add_argument("--lines", type=int, default=300)
    parser.add_argument("--noises", default="1,5")
    parser.add_argument("--figure", default=None, help="also draw the worst ratios against the separation into this PNG")
    args = parser.parse_args()
    rows = []
    print("separation  residues  noise  | worst ratio per mode (a1 a0 b1 b0 max) | truth in | verified | groups | time")
    worst_all = 0.0
    for sep in [float(s) for s in args.separations.split(",")]:
        for residues, name in (((4.0, -2.5), "opposite"), ((4.0, 2.5), "same")):
            for noise in [float(x) for x in args.noises.split(",")]:
                result, ratio, inside, elapsed = one_case(sep, residues, noise, args.lines)
                worst = np.max(ratio, axis=1)
                worst_all = max(worst_all, float(np.max(ratio)))
                rows.append((sep, name, noise, float(np.max(ratio))))
                print(f"{sep * 100:6.1f} %   {name:8s}  {noise:3.0f}x   | " + "  ".join(f"{v:5.2f}" for v in worst)
                      + f" | {inside!s:5} | {bool(result.verified.all())!s:5} | {[tuple(k + 1 for k in g) for g in result.groups]} | {elapsed:6.1f} s",
                      flush=True)
    print(f"worst ratio over every case and parameter: {worst_all:.2f}")
    if args.figure:
        ratio_figure(rows, args.figure)
        print(f"figure: {args.figure}")
    for sep in (0.03,):
        result, ratio, inside, elapsed = one_case(sep, (4.0, -2.5), 1.0, 1200)
        print(f"1,200 lines, {sep * 100:.0f} % pair: {elapsed:.1f} s, worst ratio {np.max(ratio):.2f}, truth inside {inside}")
    result, ratio, inside, elapsed = one_case(0.03, (4.0, -2.5), 1.0, args.lines, groups=False)
    print(f"for comparison, chapter 3's one-mode split alone on the 3 % pair: worst ratio {np.max(ratio):.0f} ({elapsed:.1f} s)")


if __name__ == "__main__":
    main()
