"""Numerical utilities shared by every layer (BLAS thread control)."""
