"""Mixed-mu upper bound with D and G scalings (thesis Definition 2.2, Lemma 2.1, eq. 2.13-2.16).

For a structure of ``p`` real scalars followed by complex scalars (eq. 2.11), the bound at one
frequency is

    beta(M) = inf_{D > 0, G real} sqrt( lambda_max( M_D^* M_D + j (G M_D - M_D^* G) ) ),
    M_D = D M D^{-1}                                                             (eq. 2.15)

with ``D = diag(d_i)`` (eq. 2.13) and ``G = diag(g_1..g_p, 0..0)`` (eq. 2.14). Any ``(D, G)``
gives a valid upper bound on mu, so every value returned here is evaluated *exactly* at the
scalings returned (a certificate), whatever the optimiser's accuracy.

Algorithm (ours): all frequencies are solved at once, vectorised over the frequency axis.
Variables are ``y = log d`` (``y_1 = 0``) and ``g``; the nonsmooth ``lambda_max`` is replaced by
the smooth log-sum-exp of the eigenvalues, ``f_tau = tau log sum_i exp(lambda_i / tau)``
(``lambda_max <= f_tau <= lambda_max + tau log n``), whose gradient needs one Hermitian eigen
decomposition (Theorem 4.2 applied to each eigenvalue, weighted by its softmax weight). It is
minimised by BFGS with Armijo backtracking while ``tau`` is driven to ``1e-7`` of the value, starting
from the Perron-Frobenius ``D`` of ``|M|``. Each matrix is first normalised by its largest
singular value so that one set of tolerances fits every frequency.

The certificate in the form of Lemma 2.1 (eq. 2.16, and of SLICOT AB13MD) is
``M^* D_L M + j (G_L M - M^* G_L) <= beta^2 D_L`` with ``D_L = D^2`` and ``G_L = D^2 G``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MuStructure:
    """``n_real`` real scalar blocks followed by ``n_complex`` complex scalar blocks (eq. 2.11)."""

    n_real: int
    n_complex: int

    def __post_init__(self):
        if self.n_real < 0 or self.n_complex < 0 or self.n_real + self.n_complex < 1:
            raise ValueError(f"MuStructure: expected n_real, n_complex >= 0 with a positive sum, found {self.n_real}, {self.n_complex}")

    @property
    def size(self) -> int:
        return self.n_real + self.n_complex


@dataclass(frozen=True)
class MixedMuBound:
    """Upper bound of Definition 2.2 at each frequency, with its scalings and eigen-structure.

    Attributes
    ----------
    beta : np.ndarray, shape (K,)
        The upper bound ``sqrt(lambda_max(H))``, evaluated exactly at the returned scalings.
    d : np.ndarray, shape (K, n)
        ``D`` of eq. (2.15) (``M_D = D M D^{-1}``), normalised to ``d_1 = 1``.
    g : np.ndarray, shape (K, n)
        ``G`` of eq. (2.15) (zero on complex blocks).
    eigenvalues : np.ndarray, shape (K, n)
        Eigenvalues of ``H = M_D^* M_D + j(G M_D - M_D^* G)`` (eq. 4.40), descending.
    eigenvectors : np.ndarray, shape (K, n, n)
        Matching orthonormal eigenvectors ``U`` (columns).
    """

    beta: np.ndarray
    d: np.ndarray
    g: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray

    @property
    def lmi_d(self) -> np.ndarray:
        """``D_L = D^2`` of the Lemma 2.1 (eq. 2.16) certificate."""
        return self.d**2

    @property
    def lmi_g(self) -> np.ndarray:
        """``G_L = D^2 G`` of the Lemma 2.1 (eq. 2.16) certificate."""
        return self.d**2 * self.g


def scaled_hermitian(M: np.ndarray, d: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``H = M_D^* M_D + j (G M_D - M_D^* G)`` with ``M_D = D M D^{-1}`` (eq. 2.15, 4.40); batched."""
    MD = M * (d[..., :, None] / d[..., None, :])
    MDh = np.conj(np.swapaxes(MD, -1, -2))
    GM = g[..., :, None] * MD
    return MDh @ MD + 1j * (GM - np.conj(np.swapaxes(GM, -1, -2)))


def bound_at_scalings(M: np.ndarray, d: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``sqrt(lambda_max(H))`` for given scalings: a valid mu upper bound for any ``d > 0``, real ``g``."""
    lam = np.linalg.eigvalsh(scaled_hermitian(M, d, g))[..., -1]
    return np.sqrt(np.maximum(lam, 0.0))


def _perron_start(A: np.ndarray) -> np.ndarray:
    """``y = log d`` from the Perron vectors of ``|M|`` (``D = diag(sqrt(y_left / x_right))``)."""
    B = np.abs(A) + 1e-12 * np.abs(A).max(axis=(-1, -2), keepdims=True) + 1e-300
    n = B.shape[-1]
    x = np.ones(B.shape[:-1])
    yl = np.ones(B.shape[:-1])
    for _ in range(30 if n > 1 else 0):
        x = np.einsum("kij,kj->ki", B, x)
        x /= x.sum(axis=-1, keepdims=True)
        yl = np.einsum("kji,kj->ki", B, yl)
        yl /= yl.sum(axis=-1, keepdims=True)
    y = 0.5 * (np.log(yl) - np.log(x))
    y -= y[:, :1]
    return y


class _Problem:
    """Smoothed objective and gradient, vectorised over the leading (frequency) axis."""

    def __init__(self, M: np.ndarray, structure: MuStructure):
        self.M = M
        self.n = M.shape[-1]
        self.p = structure.n_real
        self.ny = self.n - 1

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        K = x.shape[0]
        y = np.concatenate([np.zeros((K, 1)), x[:, : self.ny]], axis=1)
        g = np.zeros((K, self.n))
        g[:, : self.p] = x[:, self.ny :]
        return np.exp(y), g

    def eig(self, x: np.ndarray, idx: np.ndarray):
        d, g = self.unpack(x)
        M = self.M[idx]
        MD = M * (d[:, :, None] / d[:, None, :])
        GM = g[:, :, None] * MD
        H = np.conj(np.swapaxes(MD, -1, -2)) @ MD + 1j * (GM - np.conj(np.swapaxes(GM, -1, -2)))
        lam, U = np.linalg.eigh(H)
        return lam, U, MD, g

    def value(self, x, idx, tau):
        lam = np.linalg.eigvalsh(scaled_hermitian(self.M[idx], *self.unpack(x)))
        top = lam[:, -1]
        return top + tau * np.log(np.exp((lam - top[:, None]) / tau[:, None]).sum(axis=1)), top

    def value_grad(self, x, idx, tau):
        lam, U, MD, g = self.eig(x, idx)
        top = lam[:, -1]
        e = np.exp((lam - top[:, None]) / tau[:, None])
        s = e.sum(axis=1)
        f = top + tau * np.log(s)
        w = e / s[:, None]  # softmax weights of the eigenvalues
        V = MD @ U
        MDh = np.conj(np.swapaxes(MD, -1, -2))
        W = MDh @ V
        Z = MDh @ (g[:, :, None] * U)
        Uc = np.conj(U)
        # d lambda_i / d y_k (eq. 4.27 per eigenvalue) and d lambda_i / d g_k
        dy = 2.0 * (np.abs(V) ** 2 - np.real(np.conj(W) * U)) - 2.0 * np.imag(g[:, :, None] * Uc * V - np.conj(Z) * U)
        dg = -2.0 * np.imag(Uc[:, : self.p, :] * V[:, : self.p, :])
        grad = np.concatenate([np.einsum("kji,ki->kj", dy[:, 1:, :], w), np.einsum("kji,ki->kj", dg, w)], axis=1)
        return f, top, grad


def mixed_mu_upper(
    M: np.ndarray,
    structure: MuStructure,
    tol: float = 1e-7,
    max_iter: int = 400,
) -> MixedMuBound:
    """Mixed-mu upper bound (Definition 2.2) for a stack of matrices, all solved at once.

    Parameters
    ----------
    M : np.ndarray, shape (K, n, n) or (n, n)
        Closed-loop matrices ``M(j omega_k)``; blocks ordered real first (eq. 2.11).
    structure : MuStructure
        Numbers of real and complex scalar blocks.
    tol : float
        Final smoothing ``tau`` relative to the (normalised) value; the bound is within about
        ``tol log n`` of the smoothed optimum reached.
    max_iter : int
        Cap on BFGS iterations.

    Returns
    -------
    MixedMuBound
        ``beta`` evaluated exactly at the returned scalings (always a valid upper bound).

    Examples
    --------
    >>> import numpy as np
    >>> M = np.array([[0.0, 2.0], [0.5, 0.0]])
    >>> round(float(mixed_mu_upper(M, MuStructure(0, 2)).beta[0]), 6)  # sqrt(2 * 0.5)
    1.0
    """
    M = np.asarray(M, dtype=complex)
    single = M.ndim == 2
    if single:
        M = M[None]
    if M.ndim != 3 or M.shape[1] != M.shape[2] or M.shape[1] != structure.size:
        raise ValueError(f"M: expected shape (K, {structure.size}, {structure.size}), found {M.shape}")
    K, n = M.shape[0], M.shape[1]
    scale = np.linalg.norm(M, ord=2, axis=(1, 2))
    scale = np.where(scale > 0, scale, 1.0)
    Mn = M / scale[:, None, None]
    prob = _Problem(Mn, structure)
    nv = prob.ny + prob.p
    x = np.concatenate([_perron_start(Mn)[:, 1:], np.zeros((K, prob.p))], axis=1)
    if nv > 0:
        x = _bfgs(prob, x, tol, max_iter)
    d, g = prob.unpack(x)
    lam, U, _, _ = prob.eig(x, np.arange(K))
    lam = lam[:, ::-1] * (scale**2)[:, None]
    U = U[:, :, ::-1]
    beta = np.sqrt(np.maximum(lam[:, 0], 0.0))
    g = g * scale[:, None]
    return MixedMuBound(beta=beta, d=d, g=g, eigenvalues=lam, eigenvectors=U)


def _bfgs(prob: _Problem, x: np.ndarray, tol: float, max_iter: int) -> np.ndarray:
    """Batched BFGS on the smoothed ``lambda_max`` with a decreasing smoothing ``tau``."""
    K, nv = x.shape
    allidx = np.arange(K)
    tau = np.full(K, 1e-2)
    f, top, gr = prob.value_grad(x, allidx, tau)
    best_x, best_top = x.copy(), top.copy()
    Hinv = np.broadcast_to(np.eye(nv), (K, nv, nv)).copy() * 0.1
    active = np.ones(K, dtype=bool)
    tau_final = tol
    stall = np.zeros(K, dtype=int)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        xa, fa, ga, Ha, ta = x[idx], f[idx], gr[idx], Hinv[idx], tau[idx]
        dirn = -np.einsum("kij,kj->ki", Ha, ga)
        slope = np.einsum("ki,ki->k", dirn, ga)
        bad = slope >= 0
        if np.any(bad):  # reset to steepest descent
            Ha[bad] = np.eye(nv) * 0.1
            dirn[bad] = -0.1 * ga[bad]
            slope[bad] = np.einsum("ki,ki->k", dirn[bad], ga[bad])
        # cap the step in the log-d / g space
        nrm = np.linalg.norm(dirn, axis=1)
        dirn *= np.minimum(1.0, 2.0 / np.maximum(nrm, 1e-300))[:, None]
        slope = np.einsum("ki,ki->k", dirn, ga)
        step = np.ones(idx.size)
        xn = xa + dirn
        fn, topn = prob.value(xn, idx, ta)
        todo = fn > fa + 1e-4 * step * slope
        for _ls in range(30):
            if not np.any(todo):
                break
            step[todo] *= 0.3
            t = np.flatnonzero(todo)
            xn[t] = xa[t] + step[t, None] * dirn[t]
            fn_t, top_t = prob.value(xn[t], idx[t], ta[t])
            fn[t], topn[t] = fn_t, top_t
            todo[t] = fn_t > fa[t] + 1e-4 * step[t] * slope[t]
        fn, topn, gn = prob.value_grad(xn, idx, ta)
        s = xn - xa
        yv = gn - ga
        sy = np.einsum("ki,ki->k", s, yv)
        ok = sy > 1e-14 * np.linalg.norm(s, axis=1) * np.linalg.norm(yv, axis=1) + 1e-300
        if np.any(ok):
            o = np.flatnonzero(ok)
            rho = 1.0 / sy[o]
            I = np.eye(nv)[None]
            V = I - rho[:, None, None] * np.einsum("ki,kj->kij", s[o], yv[o])
            Ha[o] = V @ Ha[o] @ np.swapaxes(V, 1, 2) + rho[:, None, None] * np.einsum("ki,kj->kij", s[o], s[o])
        x[idx], f[idx], gr[idx], Hinv[idx] = xn, fn, gn, Ha
        improved = topn < best_top[idx]
        bi = idx[improved]
        best_top[bi], best_x[bi] = topn[improved], xn[improved]
        # progress test on the smoothed value; then shrink tau
        small = (fa - fn) <= 1e-3 * ta
        stall[idx] = np.where(small, stall[idx] + 1, 0)
        shrink = idx[(stall[idx] >= 2) | (np.linalg.norm(gn, axis=1) < 10 * ta)]
        if shrink.size:
            done = shrink[tau[shrink] <= tau_final * 1.0001]
            active[done] = False
            more = shrink[tau[shrink] > tau_final * 1.0001]
            if more.size:
                tau[more] = np.maximum(tau[more] * 0.1, tau_final)
                stall[more] = 0
                f[more], _, gr[more] = prob.value_grad(x[more], more, tau[more])
    return best_x
