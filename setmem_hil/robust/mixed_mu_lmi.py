"""Reference mixed-mu upper bound: the LMI of Lemma 2.1 (eq. 2.16) solved with Clarabel.

For fixed ``beta`` the condition

    M^* D M + j (G M - M^* G) <= beta^2 D,      D = diag(d) >= I,  G = diag(g_1..g_p, 0..0)

is an LMI in ``(d, g)``. We solve ``min t`` s.t. ``M^* D M + j(G M - M^* G) - beta^2 D <= t I``
with ``trace(D) = n`` (the condition is homogeneous, so this normalisation is free): always
feasible, and ``t < 0`` iff ``beta`` can be lowered. A Hermitian ``X = X_r + j X_i`` is PSD iff the real symmetric
``[[X_r, -X_i], [X_i, X_r]]`` is, which Clarabel's PSD triangle cone takes. The smallest
``beta`` (a generalised-eigenvalue problem) is found by a Dinkelbach-type iteration: solve at the
current value, move to the exact generalised eigenvalue of the new certificate, repeat until it
stops improving. The returned value is the exact generalised eigenvalue at the best certificate,
so it is a valid upper bound whatever the tolerances.

This is slow (one conic solve per iteration) and serves as the independent second
formulation in tests and in ``benchmarks/mu_grid.py``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from setmem_hil.errors import SolverError
from setmem_hil.robust.mixed_mu import MuStructure, _perron_start


def _svec_index(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row/column indices and scale of Clarabel's svec (upper triangle, columnwise, sqrt 2)."""
    rows, cols = [], []
    for j in range(m):
        for i in range(j + 1):
            rows.append(i)
            cols.append(j)
    rows_a, cols_a = np.array(rows), np.array(cols)
    scale = np.where(rows_a == cols_a, 1.0, np.sqrt(2.0))
    return rows_a, cols_a, scale


def _embed(X: np.ndarray) -> np.ndarray:
    return np.block([[X.real, -X.imag], [X.imag, X.real]])


def _basis(M: np.ndarray, p: int):
    """Hermitian coefficient matrices of ``M^* D M + j (G M - M^* G)`` and of ``D``."""
    n = M.shape[0]
    A_d, B_d, A_g = [], [], []
    for i in range(n):
        E = np.zeros((n, n))
        E[i, i] = 1.0
        A_d.append(M.conj().T @ E @ M)
        B_d.append(E)
    for k in range(p):
        E = np.zeros((n, n))
        E[k, k] = 1.0
        A_g.append(1j * (E @ M - M.conj().T @ E))
    return A_d, B_d, A_g


def _min_margin(M: np.ndarray, p: int, beta: float, settings) -> tuple[float, np.ndarray, np.ndarray] | None:
    """``min t`` s.t. ``M^* D M + j (G M - M^* G) - beta^2 D <= t I``, ``trace(D) = n``, ``D >= 0``.

    ``t < 0`` iff ``beta`` is above the bound; always feasible, so no infeasibility detection.
    """
    import clarabel

    n = M.shape[0]
    A_d, B_d, A_g = _basis(M, p)
    rows, cols, scale = _svec_index(2 * n)
    # variables x = (d, g, t); s = svec(beta^2 D - A(x) + t I) >= 0 written as s = b - A x
    cols_list = []
    for Ad, Bd in zip(A_d, B_d):
        S = _embed(beta**2 * Bd - Ad)
        cols_list.append(S[rows, cols] * scale)
    for Ag in A_g:
        S = _embed(-Ag)
        cols_list.append(S[rows, cols] * scale)
    I2 = np.eye(2 * n)
    cols_list.append(I2[rows, cols] * scale)
    Apsd = -np.column_stack(cols_list)
    nv = n + p + 1
    Aeq = np.zeros((1, nv))
    Aeq[0, :n] = 1.0
    Anon = np.zeros((n, nv))
    Anon[np.arange(n), np.arange(n)] = -1.0
    A = sp.csc_matrix(np.vstack([Aeq, Anon, Apsd]))
    b = np.concatenate([[float(n)], np.zeros(n), np.zeros(Apsd.shape[0])])
    q = np.zeros(nv)
    q[-1] = 1.0
    P = sp.csc_matrix((nv, nv))
    cones = [clarabel.ZeroConeT(1), clarabel.NonnegativeConeT(n), clarabel.PSDTriangleConeT(2 * n)]
    sol = clarabel.DefaultSolver(P, q, A, b, cones, settings).solve()
    status = str(sol.status)
    if status not in ("Solved", "AlmostSolved"):
        if "Infeasible" in status:  # cannot happen for this always-feasible problem
            raise SolverError(f"mixed-mu LMI (Clarabel): status {status} at beta = {beta:.6g}")
        return None  # numerical trouble near the optimum: the caller keeps its best certificate
    x = np.array(sol.x)
    return float(x[-1]), x[:n], x[n : n + p]


def generalized_bound(M: np.ndarray, p: int, d_lmi: np.ndarray, g_lmi: np.ndarray) -> float:
    """``sqrt(lambda_max(D^{-1/2} (M^* D M + j (G M - M^* G)) D^{-1/2}))`` for given ``(D, G)``."""
    n = M.shape[0]
    G = np.zeros(n)
    G[:p] = g_lmi[:p]
    A = M.conj().T @ (d_lmi[:, None] * M) + 1j * (G[:, None] * M - M.conj().T * G[None, :])
    s = 1.0 / np.sqrt(d_lmi)
    lam = np.linalg.eigvalsh(s[:, None] * A * s[None, :])[-1]
    return float(np.sqrt(max(lam, 0.0)))


def mixed_mu_upper_lmi(M: np.ndarray, structure: MuStructure, rtol: float = 1e-7, max_bisections: int = 40):
    """Mixed-mu upper bound of Lemma 2.1 for one matrix, by iterated Clarabel LMI solves.

    Parameters
    ----------
    M : np.ndarray, shape (n, n)
    structure : MuStructure
    rtol : float
        Relative improvement below which the iteration stops.

    Returns
    -------
    beta : float
        Exact bound at the best certificate.
    d_lmi, g_lmi : np.ndarray
        The certificate ``(D, G)`` of eq. (2.16).

    Examples
    --------
    >>> import numpy as np
    >>> M = np.array([[0.0, 2.0], [0.5, 0.0]])
    >>> round(mixed_mu_upper_lmi(M, MuStructure(0, 2))[0], 4)
    1.0
    """
    import clarabel

    M = np.asarray(M, dtype=complex)
    n = M.shape[0]
    if M.shape != (structure.size, structure.size):
        raise ValueError(f"M: expected shape ({structure.size}, {structure.size}), found {M.shape}")
    p = structure.n_real
    # scale first (mu is invariant under M -> T M T^{-1} / s up to the factor s): Perron D of |M|
    # and the largest singular value; the certificate is mapped back at the end
    s_norm = float(np.linalg.norm(M, 2)) or 1.0
    T = np.exp(_perron_start(M[None] / s_norm)[0])
    Mo = M
    M = (T[:, None] * M / T[None, :]) / s_norm
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    best_d, best_g = np.ones(n), np.zeros(p)
    best = generalized_bound(M, p, best_d, np.zeros(n))
    # Dinkelbach-style iteration: solve the margin LMI at the current value, move to the exact
    # generalised eigenvalue of the new certificate, stop when it no longer improves
    for _ in range(max_bisections):
        sol = _min_margin(M, p, best * (1.0 - 0.5 * rtol), settings)
        if sol is None:
            break
        t, d, g = sol
        if t >= 0.0:
            break
        d = np.maximum(d, 1e-12)
        gfull = np.zeros(n)
        gfull[:p] = g
        val = generalized_bound(M, p, d, gfull)
        if val >= best * (1.0 - rtol):
            if val < best:
                best, best_d, best_g = val, d, g
            break
        best, best_d, best_g = val, d, g
    gout = np.zeros(n)
    gout[:p] = best_g
    d_lmi = T**2 * best_d
    g_lmi = s_norm * T**2 * gout
    # the exact value on the original matrix at the mapped certificate
    return generalized_bound(Mo, p, d_lmi, g_lmi), d_lmi, g_lmi
