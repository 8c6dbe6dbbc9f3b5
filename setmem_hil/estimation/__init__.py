"""Estimation of one frequency-response point from sampled data (sine fit with modelled transients).

The sine fit's names are loaded on first use (a module that needs a light part of the package,
such as a record kind's name, does not load scipy.optimize).
"""

__all__ = ["SineFit", "fit_sine", "fit_sine_with_transients"]


def __getattr__(name: str):
    if name in __all__:
        from setmem_hil.estimation import sine_fit

        return getattr(sine_fit, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
