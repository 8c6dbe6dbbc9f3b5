"""Mixed-mu lower bound by a power-type fixed-point iteration (to report the gap to the upper bound).

Any ``Delta`` in the structure (real scalars in ``[-1, 1]``, complex scalars in the unit disc,
eq. 2.11) and any *real* eigenvalue ``lambda`` of ``M Delta`` give ``det(I - M Delta / lambda) = 0``
with ``sigma_max(Delta / lambda) <= 1 / |lambda|``, hence ``mu(M) >= |lambda|`` (Definition 2.1).
With the real blocks at zero, every eigenvalue can be rotated onto the real axis by a common phase
of the complex blocks, so ``|lambda|`` of any eigenvalue counts.

The iteration (in the spirit of Young and Doyle's power algorithm) moves each block to the
vertex / phase that increases the dominant eigenvalue to first order:
``d lambda / d delta_k = (y^* M)_k x_k / (y^* x)`` (``x``, ``y`` right and left eigenvectors).
For the real blocks we then search the common phase ``theta`` of the complex blocks for which the
tracked eigenvalue of ``M diag(delta_R, e^{j theta} delta_C)`` is real (secant on its imaginary
part), and keep it only if it is real to 1e-10 relative. Every value returned is attained by an
explicit ``Delta``: a true lower bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.robust.mixed_mu import MuStructure


@dataclass(frozen=True)
class MixedMuLower:
    """Lower bound per matrix and the perturbation direction attaining it.

    Attributes
    ----------
    beta : np.ndarray, shape (K,)
        Lower bound on mu.
    delta : np.ndarray, shape (K, n)
        Diagonal of a ``Delta`` in the unit ball of the structure with
        ``det(I - M diag(delta) / beta) = 0`` (``beta > 0``).
    """

    beta: np.ndarray
    delta: np.ndarray


def _dominant(MD: np.ndarray, prefer_real_axis: bool):
    lam, X = np.linalg.eig(MD)
    score = np.abs(lam) if not prefer_real_axis else np.abs(lam) - 2.0 * np.abs(lam.imag)
    j = np.argmax(score, axis=1)
    K = MD.shape[0]
    lam1 = lam[np.arange(K), j]
    x = X[np.arange(K), :, j]
    Y = np.linalg.inv(X)
    y = np.conj(Y[np.arange(K), j, :])  # left eigenvector: y^* M D = lambda y^*
    return lam1, x, y


def _complex_only(M: np.ndarray, n_iter: int) -> tuple[np.ndarray, np.ndarray]:
    """Max over unit-modulus ``delta`` of ``rho(M diag(delta))`` (all blocks complex): local ascent."""
    K, n = M.shape[0], M.shape[1]
    delta = np.ones((K, n), dtype=complex)
    best = np.zeros(K)
    best_delta = delta.copy()
    for _ in range(n_iter):
        lam, x, y = _dominant(M * delta[:, None, :], False)
        val = np.abs(lam)
        better = val > best
        # rotate the (all complex) blocks so that the eigenvalue is real positive
        phase = np.exp(-1j * np.angle(lam))
        best[better], best_delta[better] = val[better], delta[better] * phase[better, None]
        c = (np.conj(y)[:, :, None] * M).sum(axis=1) * x  # (y^* M)_k x_k, up to the common y^* x
        c = c / np.einsum("ki,ki->k", np.conj(y), x)[:, None]
        # d|lambda| ~ Re(conj(lambda) c_k d delta_k): align each delta_k with lambda conj(c_k)
        tgt = lam[:, None] * np.conj(c)
        mag = np.abs(tgt)
        delta = np.where(mag > 1e-300, tgt / np.where(mag > 0, mag, 1.0), delta)
    return best, best_delta


def mixed_mu_lower(M: np.ndarray, structure: MuStructure, n_iter: int = 20, search_real: bool = True) -> MixedMuLower:
    """Lower bound on mixed mu for a stack of matrices (Definition 2.1).

    Parameters
    ----------
    M : np.ndarray, shape (K, n, n) or (n, n)
    structure : MuStructure
        Real scalar blocks first, then complex scalars.
    n_iter : int
        Fixed-point iterations per phase.
    search_real : bool
        Also search with the real blocks at vertices (costlier); otherwise the real blocks
        stay at zero (still a valid lower bound).

    Returns
    -------
    MixedMuLower

    Examples
    --------
    >>> import numpy as np
    >>> M = np.array([[0.0, 2.0], [0.5, 0.0]])
    >>> round(float(mixed_mu_lower(M, MuStructure(0, 2)).beta[0]), 9)
    1.0
    """
    M = np.asarray(M, dtype=complex)
    if M.ndim == 2:
        M = M[None]
    K, n = M.shape[0], M.shape[1]
    if n != structure.size:
        raise ValueError(f"M: expected blocks of size {structure.size}, found {n}")
    p = structure.n_real
    best = np.zeros(K)
    best_delta = np.zeros((K, n), dtype=complex)
    if structure.n_complex:
        Mc = M[:, p:, p:]
        b, dc = _complex_only(Mc, n_iter)
        best = b
        best_delta[:, p:] = dc
    if p and search_real:
        b, dl = _mixed_search(M, p, n_iter, best_delta)
        better = b > best
        best[better], best_delta[better] = b[better], dl[better]
    return MixedMuLower(beta=best, delta=best_delta)


def _mixed_search(M: np.ndarray, p: int, n_iter: int, start: np.ndarray):
    """Fixed-point ascent with real blocks at vertices, then a real-axis search over the phase."""
    K, n = M.shape[0], M.shape[1]
    delta = start.copy()
    delta[:, :p] = 1.0
    if n == p:
        delta = delta.real.astype(complex)
    for _ in range(n_iter):
        lam, x, y = _dominant(M * delta[:, None, :], True)
        c = (np.conj(y)[:, :, None] * M).sum(axis=1) * x
        c = c / np.einsum("ki,ki->k", np.conj(y), x)[:, None]
        tgt = np.conj(lam)[:, None] * c  # first-order change of |lambda|^2 direction
        real_part = np.sign(tgt[:, :p].real)
        real_part[real_part == 0] = 1.0
        delta[:, :p] = real_part
        if n > p:
            t = lam[:, None] * np.conj(c[:, p:])
            mag = np.abs(t)
            delta[:, p:] = np.where(mag > 0, t / np.where(mag > 0, mag, 1.0), delta[:, p:])
    return _real_axis_value(M, delta, p)


def _real_axis_value(M: np.ndarray, delta: np.ndarray, p: int):
    """Largest ``|lambda|`` over real eigenvalues of ``M diag(delta_R, e^{j theta} delta_C)``."""
    K, n = M.shape[0], M.shape[1]
    best = np.zeros(K)
    best_delta = delta.copy()
    thetas = np.linspace(0.0, 2 * np.pi, 24, endpoint=False) if n > p else np.zeros(1)
    rot = np.ones((thetas.size, n), dtype=complex)
    rot[:, p:] = np.exp(1j * thetas)[:, None]
    D = delta[:, None, :] * rot[None, :, :]  # (K, T, n)
    lam = np.linalg.eigvals(M[:, None, :, :] * D[:, :, None, :])  # (K, T, n)
    # exact real eigenvalues (pure real structure, or lucky phases)
    real_ok = np.abs(lam.imag) <= 1e-10 * np.maximum(np.abs(lam), 1e-300)
    score0 = np.where(real_ok, np.abs(lam), 0.0)
    flat0 = score0.reshape(K, -1).argmax(axis=1)
    t0, e0 = np.unravel_index(flat0, (thetas.size, n))
    cand = score0.reshape(K, -1).max(axis=1)
    upd = cand > best
    best[upd] = cand[upd]
    lam0 = lam[np.arange(K), t0, e0]
    best_delta[upd] = D[upd, t0[upd]] * np.sign(lam0.real[upd])[:, None]
    if n == p:
        return best, best_delta
    # secant refinement from the grid phase whose eigenvalue is closest to the real axis,
    # among the larger eigenvalues
    ang = np.abs(np.angle(lam * np.sign(lam.real + (lam.real == 0))))  # angle to the real axis
    score = np.abs(lam) * (ang < 0.2)
    flat = score.reshape(K, -1).argmax(axis=1)
    ti, ei = np.unravel_index(flat, (thetas.size, n))
    th0 = thetas[ti]
    target = lam[np.arange(K), ti, ei]
    th1 = th0 + 1e-3
    def tracked(th, prev):
        Dr = delta.copy()
        Dr[:, p:] = Dr[:, p:] * np.exp(1j * th)[:, None]
        l = np.linalg.eigvals(M * Dr[:, None, :])
        j = np.argmin(np.abs(l - prev[:, None]), axis=1)
        return l[np.arange(K), j], Dr
    l0, _ = tracked(th0, target)
    l1, D1 = tracked(th1, l0)
    for _ in range(12):
        f0, f1 = l0.imag, l1.imag
        den = np.where(np.abs(f1 - f0) > 1e-300, f1 - f0, 1e-300)
        th2 = th1 - f1 * (th1 - th0) / den
        th2 = np.where(np.isfinite(th2) & (np.abs(th2 - th1) < 1.0), th2, th1)
        l2, D2 = tracked(th2, l1)
        th0, l0, th1, l1, D1 = th1, l1, th2, l2, D2
    ok = np.abs(l1.imag) <= 1e-10 * np.maximum(np.abs(l1), 1e-300)
    val = np.where(ok, np.abs(l1), 0.0)
    upd = val > best
    best[upd] = val[upd]
    best_delta[upd] = D1[upd] * np.sign(l1.real[upd])[:, None]
    return best, best_delta
