"""Per-thread single-threaded BLAS for small numerics (a performance guard, no global state).

The sine fits and the exact discretisation multiply tall, thin or small matrices; multithreaded
OpenBLAS makes them up to 30x slower on a loaded 2-core machine. numpy and scipy bundle their
own OpenBLAS; ``openblas_set_num_threads_local`` sets the count for the calling thread only and
returns the previous one, which we restore. Without a bundled OpenBLAS this does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import os

import numpy as np


def _openblas_libraries() -> list:
    """numpy's and scipy's bundled OpenBLAS (for per-thread thread-count control), if found."""
    libs = []
    for pkg in (np, __import__("scipy")):
        root = os.path.dirname(os.path.dirname(pkg.__file__))
        name = pkg.__name__
        for path in glob.glob(os.path.join(root, f"{name}.libs", "libscipy_openblas*.so")):
            try:
                lib = ctypes.CDLL(path)
                fn = lib.openblas_set_num_threads_local
            except (OSError, AttributeError):
                continue
            fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
            libs.append(fn)
    return libs


_BLAS_SETTERS = _openblas_libraries()


@contextlib.contextmanager
def blas_one_thread():
    """Run BLAS single-threaded in this thread (restored afterwards).

    The fits multiply tall, thin matrices (thousands x ~10); multithreaded OpenBLAS makes them
    up to 30x slower on a loaded 2-core machine. ``openblas_set_num_threads_local`` affects
    only the calling thread and returns the previous setting, so no global state is left.
    """
    old = [fn(1) for fn in _BLAS_SETTERS]
    try:
        yield
    finally:
        for fn, n in zip(_BLAS_SETTERS, old):
            fn(n)


def single_thread_blas(func):
    """Decorator: run ``func`` with single-threaded BLAS in the calling thread."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with blas_one_thread():
            return func(*args, **kwargs)

    return wrapper
