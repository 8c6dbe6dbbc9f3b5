"""mu-sensitivities from one eigen-decomposition (thesis Theorems 4.2-4.3, steps 1-5 of 4.2.2).

Shrinking the normalised size of uncertainty ``i`` by ``(1 - eps)^2`` is ``M -> A M A`` with
``A = diag(1, .., 1 - eps, .., 1)`` (Lemma 2.2, figure 2-2). With the optimal scalings held fixed
(Lemma 4.1, the envelope argument), ``M_D -> A M_D A`` (diagonal matrices commute), so

    dM_D / d eps = -(E_i M_D + M_D E_i),                         E_i = e_i e_i^T
    X = dM_D^* M_D + M_D^* dM_D + j (G dM_D - dM_D^* G)          (eq. 4.41)

and the derivative of ``beta^2`` is the largest eigenvalue of ``U_1^* X U_1`` (Theorem 4.3),
where ``U_1`` spans the eigenspace of the (possibly repeated) top eigenvalue of
``H = M_D^* M_D + j (G M_D - M_D^* G)`` (eq. 4.40). Dividing by ``2 beta`` gives ``d beta / d eps``.

Convention of this package (and appendix B): the *sensitivity* is ``s_i = -d mu_peak / d eps``,
which is ``>= 0`` by Lemma 2.2.
"""

from __future__ import annotations

import numpy as np

from setmem_hil.robust.mixed_mu import MixedMuBound


def top_eigenspace(eigenvalues: np.ndarray, eigenvectors: np.ndarray, rtol: float = 1e-4) -> np.ndarray:
    """Columns ``U_1`` for the eigenvalues within ``rtol`` (relative) of the largest (step 2 of 4.2.2)."""
    lam = np.asarray(eigenvalues)
    top = lam[0]
    m = int(np.count_nonzero(lam >= top - rtol * max(abs(top), 1e-300)))
    return eigenvectors[:, : max(m, 1)]


def beta_derivatives(M: np.ndarray, bound: MixedMuBound, index: int = 0, rtol: float = 1e-4) -> np.ndarray:
    """``d beta / d eps_i`` for every block ``i`` at one frequency (steps 1-5 of 4.2.2).

    Parameters
    ----------
    M : np.ndarray, shape (n, n)
        The closed-loop matrix at this frequency.
    bound : MixedMuBound
        Result of :func:`~setmem_hil.robust.mixed_mu.mixed_mu_upper` (optimal scalings, eigen-structure).
    index : int
        Which frequency of ``bound`` ``M`` belongs to.
    rtol : float
        Relative tolerance deciding which top eigenvalues count as repeated.

    Returns
    -------
    np.ndarray, shape (n,)
        ``d beta / d eps`` (``<= 0`` up to rounding) for shrinking each block in turn.
    """
    d, g = bound.d[index], bound.g[index]
    beta = bound.beta[index]
    MD = np.asarray(M, dtype=complex) * (d[:, None] / d[None, :])
    U1 = top_eigenspace(bound.eigenvalues[index], bound.eigenvectors[index], rtol)
    n = MD.shape[0]
    # For each i, with P = M_D U1 and the rows of U1 / columns of M_D:
    # dM U1 = -(e_i (M_D U1)[i, :] + M_D[:, i] U1[i, :])
    P = MD @ U1  # (n, m)
    Q = MD.conj().T @ P  # M_D^* M_D U1
    R = MD.conj().T @ (g[:, None] * U1)  # M_D^* G U1
    out = np.empty(n)
    for i in range(n):
        # Y = U1^* M_D^* dM U1 = -(P^*[:, i] P[i, :] + Q^*[:, i]... ) written out:
        Pi = P[i, :]
        Ui = U1[i, :]
        # U1^* M_D^* e_i P_i  = conj(P[i,:])^T P[i,:];  U1^* M_D^* M_D e_i U_i = conj(Q[i,:])^T U_i
        Y = -(np.outer(Pi.conj(), Pi) + np.outer(Q[i, :].conj(), Ui))
        # U1^* G dM U1 = -(g_i conj(U_i)^T P_i + conj(R[i,:])^T U_i)
        S = -(g[i] * np.outer(Ui.conj(), Pi) + np.outer(R[i, :].conj(), Ui))
        X1 = Y + Y.conj().T + 1j * (S - S.conj().T)
        out[i] = np.linalg.eigvalsh(0.5 * (X1 + X1.conj().T))[-1] / (2.0 * beta) if beta > 0 else 0.0
    return out
