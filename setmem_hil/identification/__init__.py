"""Set-membership identification of the modal model (thesis chapter 3, Algorithms 3.1/3.2).

The package's names are loaded on first use, so a module that needs one part (the residue
bootstrap of ``run --check``) does not load the conic solvers.
"""

__all__ = ["IdentificationResult", "IdentifySettings", "identify"]


def __getattr__(name: str):
    if name in __all__:
        from setmem_hil.identification import algorithm

        return getattr(algorithm, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
