"""setmem-hil: set-membership identification and robust-performance-driven input design for
lightly damped flexible structures, on simulated rigs, loopback transports or real instruments.

The library surface a user needs is re-exported here (imported on first use, so the command line
starts fast): :func:`identify`, :func:`analyze_robust_performance`, :func:`run_campaign`,
:func:`load_procedure`, :func:`open_run` (a stored run in python-control's types, docs/notebook.md) and the error types of :mod:`setmem_hil.errors`. Subpackages by concept:
``model``, ``identification``, ``robust``, ``design``, ``estimation``, ``discrepancy``,
``campaign``, ``io``, ``report``, ``sweep``, ``cli``; hardware in ``setmem_hil.drivers``,
simulation in ``setmem_hil.sim_backends`` (see ARCHITECTURE.md).
"""

__version__ = "0.1.0"

from setmem_hil.errors import (  # noqa: E402  (after __version__: submodules import it)
    DeviceError,
    InconsistentDataError,
    InputFormatError,
    ProcedureError,
    SetmemError,
    SolverError,
)

_LAZY = {
    "identify": "setmem_hil.identification.algorithm",
    "analyze_robust_performance": "setmem_hil.robust.analysis",
    "run_campaign": "setmem_hil.campaign.runner",
    "load_procedure": "setmem_hil.io.procedure_file",
    "open_run": "setmem_hil.campaign.stored_run",
}

__all__ = ["__version__", *_LAZY, "SetmemError", "InputFormatError", "ProcedureError", "InconsistentDataError",
           "SolverError", "DeviceError"]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'setmem_hil' has no attribute {name!r}")
