"""Plot of a sweep: distribution of experiments-to-goal per input-design strategy (``sweep.png``).

One column per strategy: a box of the added experiments of the campaigns that reached
mu-bar < goal (the stopping rule of Algorithm 5.1, step 4), every campaign as a dot (a fixed
deterministic jitter separates equal values), campaigns that spent the budget without reaching
the goal as hollow markers above a dashed line at the budget, and failed campaigns counted in the
label. The figure of merit is the thesis's (section 6.3): how few added points reach the goal.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from setmem_hil.io.atomic_file import atomic_path


def plot_experiments_to_goal(document: dict, path: str | os.PathLike) -> Path:
    """Draw the ``sweep.json`` ``document`` into ``path`` (PNG) and return the path.

    Parameters
    ----------
    document : dict
        ``{"runs": [...], "summary": {...}, "strategies": [...], "goal": {...}}`` as written by
        :func:`setmem_hil.sweep.runner.run_sweep`.
    path : path-like
        Output file; the format follows the suffix (``.png``).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    runs = document["runs"]
    strategies = list(document.get("strategies") or dict.fromkeys(r["strategy"] for r in runs))
    designs = list(document.get("designs") or [])
    if len(designs) > 1 or document.get("lanes", strategies) != strategies:  # a sweep over designs: one column each
        strategies = list(document["lanes"])
        runs = [{**r, "strategy": f"{r['strategy']}-{r['design']}"} for r in runs]
    goal = document.get("goal", {})
    cap = goal.get("max_experiments")
    finished = [r for r in runs if not r.get("error")]
    top = cap if cap is not None else max([r["experiments_added"] for r in finished] or [1])
    above = top + max(1.0, 0.08 * top)
    rng = np.random.default_rng(0)  # jitter only; fixed so the figure is reproducible

    fig = Figure(figsize=(max(5.0, 1.6 * len(strategies) + 2.0), 4.2))
    ax = fig.add_subplot(1, 1, 1)
    labels = []
    for i, s in enumerate(strategies):
        rows = [r for r in runs if r["strategy"] == s]
        ok = [r for r in rows if not r.get("error")]
        reached = np.array([r["experiments_added"] for r in ok if r["reached_goal"]], dtype=float)
        missed = sum(1 for r in ok if not r["reached_goal"])
        failed = len(rows) - len(ok)
        if reached.size:
            ax.boxplot([reached], positions=[i], widths=0.5, showfliers=False, manage_ticks=False)
            ax.scatter(i + rng.uniform(-0.18, 0.18, reached.size), reached, s=16, color="C0", zorder=3)
        if missed:
            ax.scatter(i + rng.uniform(-0.18, 0.18, missed), np.full(missed, above), s=22,
                       facecolors="none", edgecolors="C3", zorder=3)
        label = f"{s}\n{reached.size}/{len(rows)} reached"
        if failed:
            label += f"\n{failed} failed"
        labels.append(label)
    if cap is not None:
        ax.axhline(cap + 0.5 * (above - cap), color="C3", linestyle="--", linewidth=0.8)
        ax.text(-0.55, above + 0.35 * max(1.0, 0.08 * top), f"not reached within {cap}", color="C3", ha="left",
                va="bottom", fontsize=8)
    ax.set_xticks(range(len(strategies)), labels, fontsize=8)
    ax.set_xlim(-0.6, len(strategies) - 0.4)
    ax.set_ylim(bottom=-0.5, top=above + max(2.0, 0.2 * top))
    ax.set_ylabel("added experiments to reach mu-bar < %g" % goal.get("mu_target", 1.0))
    seeds = document.get("seeds") or sorted({r["seed"] for r in runs})
    ax.set_title(f"{document.get('procedure', 'sweep')}: {len(seeds)} seeds per strategy", fontsize=10)
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    out = Path(path)
    with atomic_path(out) as tmp:  # never a half-written figure under the final name
        fig.savefig(tmp, dpi=110, format=(out.suffix.lstrip(".") or "png"))
    return out


__all__ = ["plot_experiments_to_goal"]
