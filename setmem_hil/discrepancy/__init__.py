"""Where model and data disagree: name the missing effect, add it, show the gap shrink."""

from setmem_hil.discrepancy.workflow import DiscrepancyReport, check_discrepancy

__all__ = ["DiscrepancyReport", "check_discrepancy"]
