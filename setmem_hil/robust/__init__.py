"""Uncertain plant, H2 design, mixed-mu upper bound and mu-sensitivities (thesis chapters 2 and 4)."""

from setmem_hil.robust.analysis import RobustAnalysis, analyze_robust_performance
from setmem_hil.robust.mixed_mu import mixed_mu_upper

__all__ = ["RobustAnalysis", "analyze_robust_performance", "mixed_mu_upper"]
