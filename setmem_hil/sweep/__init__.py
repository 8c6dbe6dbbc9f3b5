"""Sweeps of campaigns over seeds and strategies on Dask."""

from setmem_hil.sweep.runner import SweepResult, run_sweep

__all__ = ["SweepResult", "run_sweep"]
