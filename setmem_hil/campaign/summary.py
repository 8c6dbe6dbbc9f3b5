"""What a campaign returns: one row per iteration (figure 6-12's table) and the run's summary
(``summary.json``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["CampaignSummary", "IterationSummary"]


@dataclass(frozen=True)
class IterationSummary:
    """One row of the figure-6-12 table."""

    k: int
    n_points: int
    mu_peak: float
    mu_peak_omega: float
    next_omega: float | None
    safeguard: str
    basis: str
    compute_s: float = 0.0  # the plan's computation for this iteration (the run engine's clock)
    compute_cpu_s: float = 0.0
    rig_s: float = 0.0  # device seconds of the dwells this iteration asked for (measured after it)
    mu_peak_certified: bool = False  # mu_peak bounds mu-bar on the whole band, not only the grid
    mu_certified_intervals: int = 0
    design: str = "h2"  # the design that made the kept compensator: "robust" or "h2" (issue 38)
    floor_modes: tuple[int, ...] = ()  # modes whose box blocks every compensator (setmem_hil.model.mu_floor)
    certified_mu: float = float("inf")  # mu-bar certified on the whole band (the stopping test's value; inf: none)

    def to_document(self) -> dict:
        return {
            "k": self.k,
            "certified_mu": float(self.certified_mu) if np.isfinite(self.certified_mu) else None,
            "mu_peak": self.mu_peak,
            "mu_peak_certified": bool(self.mu_peak_certified),
            "mu_certified_intervals": int(self.mu_certified_intervals),
            "next_omega": self.next_omega,
            "n_points": self.n_points,
            "mu_peak_omega": self.mu_peak_omega,
            "safeguard": self.safeguard,
            "basis": self.basis,
            "compute_s": self.compute_s,
            "compute_cpu_s": self.compute_cpu_s,
            "rig_s": float(self.rig_s),
            "design": self.design,
            "floor_modes": [int(m) for m in self.floor_modes],
        }


@dataclass(frozen=True)
class CampaignSummary:
    """Result of :func:`setmem_hil.campaign.runner.run_campaign`; :meth:`to_document` is ``summary.json``."""

    reached_goal: bool
    final_mu_peak: float
    experiments_added: int
    iterations: tuple[IterationSummary, ...]
    strategy: str
    seed: int | None
    goal_mu: float
    max_experiments: int
    stop_reason: str
    wall_s: float = 0.0  # the run's wall time (the run engine's, filled in by the runner)
    replayed_measurements: int = 0
    rig_s: float = 0.0  # device seconds of every dwell, initial points included
    extra: dict = field(default_factory=dict)

    @property
    def compute_s_per_iteration(self) -> float:
        """Mean compute time of an iteration (identification, design, analysis, input choice)."""
        if not self.iterations:
            return 0.0
        return float(np.mean([it.compute_s for it in self.iterations]))

    def to_document(self) -> dict:
        return {
            "reached_goal": bool(self.reached_goal),
            "final_mu_peak": float(self.final_mu_peak),
            "experiments_added": int(self.experiments_added),
            "wall_s": float(self.wall_s),
            "iterations": [it.to_document() for it in self.iterations],
            "strategy": self.strategy,
            "seed": self.seed,
            "goal_mu": float(self.goal_mu),
            "max_experiments": int(self.max_experiments),
            "stop_reason": self.stop_reason,
            "compute_s_per_iteration": self.compute_s_per_iteration,
            "compute_cpu_s_per_iteration": float(np.mean([it.compute_cpu_s for it in self.iterations])) if self.iterations else 0.0,
            "replayed_measurements": int(self.replayed_measurements),
            "rig_s": float(self.rig_s),
            **self.extra,
        }
