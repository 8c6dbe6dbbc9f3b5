"""Estimation of one frequency-response point from sampled data (sine fit with modelled transients)."""

from setmem_hil.estimation.sine_fit import SineFit, fit_sine, fit_sine_with_transients

__all__ = ["SineFit", "fit_sine", "fit_sine_with_transients"]
