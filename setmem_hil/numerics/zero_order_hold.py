"""The exact discretisation of ``x' = A x + B u`` for an input held over each sample."""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["held"]


def held(A: np.ndarray, B: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(Ad, Bd)`` with ``x[k+1] = Ad x[k] + Bd u[k]``: ``expm`` of the augmented matrix
    ``[[A, B], [0, 0]] dt`` (exact for a zero-order-held ``u``; ``B`` one column or a vector)."""
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float).reshape(A.shape[0], -1)
    n, m = B.shape
    Phi = scipy.linalg.expm(np.block([[A, B], [np.zeros((m, n + m))]]) * dt_s)
    return Phi[:n, :n], Phi[:n, n:]
