"""Summary of a sweep: per-strategy statistics of experiments-to-goal (``sweep.json``).

The figure of merit is the thesis's (section 6.3): how many added experiments a campaign needed
until mu-bar < 1 (Algorithm 5.1, step 4).
"""

from __future__ import annotations

import math
import statistics
from typing import Callable, Iterable, Sequence


def _median_experiments(runs: Sequence[dict]) -> float | None:
    """Median added experiments to reach the goal; a run that did not reach it counts as infinite.

    ``None`` when fewer than half the runs reached the goal (the median is then "more than the
    budget") or there are no runs.
    """
    values = sorted(r["experiments_added"] if r["reached_goal"] else math.inf for r in runs)
    if not values:
        return None
    med = statistics.median(values)
    return float(med) if math.isfinite(med) else None


def summarize_runs(runs: Iterable[dict], strategies: Sequence[str], key: Callable[[dict], str] = lambda r: r["strategy"]) -> dict:
    """Per-strategy summary of ``sweep.json`` rows (``key``: a row's group, its strategy by default;
    ``<strategy>-<design>`` in a sweep over designs).

    For each strategy: ``runs`` (campaigns), ``failed`` (rows with ``"error"``), ``reached``
    (finished with mu-bar < goal), ``median_experiments`` (median added experiments over the
    finished runs, a run that missed the goal counting as infinitely many; ``None`` when that
    median is not finite) and ``median_experiments_reached`` (over the runs that reached it).
    """
    runs = list(runs)
    out: dict[str, dict] = {}
    for s in strategies:
        rows = [r for r in runs if key(r) == s]
        ok = [r for r in rows if not r.get("error")]
        reached = [r["experiments_added"] for r in ok if r["reached_goal"]]
        out[s] = {
            "median_experiments": _median_experiments(ok),
            "reached": len(reached),
            "runs": len(rows),
            "failed": len(rows) - len(ok),
            "median_experiments_reached": float(statistics.median(reached)) if reached else None,
        }
    return out


def format_summary_table(document: dict) -> str:
    """Plain-text per-strategy table of a ``sweep.json`` document."""
    cap = document.get("goal", {}).get("max_experiments")
    lines = [f"{'strategy':>13s} | {'runs':>4s} | {'reached':>7s} | {'failed':>6s} | {'median experiments':>18s}"]
    lines.append("-" * len(lines[0]))
    for s, row in document["summary"].items():
        med = row["median_experiments"]
        if row["runs"] == row["failed"]:
            med_s = "-"  # no finished campaign
        else:
            med_s = f"{med:g}" if med is not None else (f">{cap}" if cap is not None else "-")
        lines.append(f"{s:>13s} | {row['runs']:>4d} | {row['reached']:>7d} | {row['failed']:>6d} | {med_s:>18s}")
    return "\n".join(lines)


__all__ = ["format_summary_table", "summarize_runs"]
