"""The HTML report of a run and its figures."""

from setmem_hil.report.document import write_report

__all__ = ["write_report"]
