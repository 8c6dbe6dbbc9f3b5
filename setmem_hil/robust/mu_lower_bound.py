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

import itertools
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


def mixed_mu_lower(M: np.ndarray, structure: MuStructure, n_iter: int = 20, search_real: bool = True,
                   interior=True) -> MixedMuLower:
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
    interior : bool or array of bool, shape (K,)
        With ``search_real``: then search the real blocks' interior too (:func:`interior_search`,
        the costliest part: about 0.2 s per matrix of the 6.3.2 problem), for every matrix or
        for those marked.

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
        vertex_delta = dl.copy()  # the vertex search's direction, even where its eigenvalue was not real
        better = b > best
        best[better], best_delta[better] = b[better], dl[better]
        searched = np.broadcast_to(np.asarray(interior, dtype=bool), (K,))
        for k in np.flatnonzero(searched):  # the real blocks' interior (issue 38): a local search from several starts
            b, dl = interior_search(M[k], p, (vertex_delta[k], best_delta[k]))  # one seed for every matrix: the result does not depend on the batch
            if b > best[k]:
                best[k], best_delta[k] = b, dl
    return MixedMuLower(beta=best, delta=best_delta)


INTERIOR_STARTS = 4  # random starts of the interior search, besides the vertex search's result
SMALL_REAL_STRUCTURE = 6  # up to this many real blocks every vertex is also a start


def interior_search(M: np.ndarray, p: int, start, seed: int = 0, n_starts: int = INTERIOR_STARTS):
    """Largest real eigenvalue of ``M Delta`` with every block anywhere in its unit ball.

    The vertex search puts every real block at +-1 and every complex one on the unit circle;
    where the destabilising plant has interior parameters (the floor of a lightly damped mode:
    ``a1`` at a vertex, ``a0`` and ``b0`` inside, the unmodelled dynamics at zero, issue 38) it
    finds nothing. Here (ours, in the spirit of Young and Doyle's real-axis eigenvalue search):
    maximise ``Re lambda`` of a tracked eigenvalue of ``M diag(delta, r e^{j theta})`` subject to
    ``Im lambda = 0`` over ``delta`` in ``[-1, 1]``, ``r`` in ``[0, 1]`` and the phases ``theta``
    (SLSQP with the eigenvalue's analytic derivatives ``d lambda / d Delta_k = (y^* M)_k x_k /
    (y^* x)``), from the vertex search's result, the origin and random points; then make the
    eigenvalue exactly real by a secant on the variable that moves its imaginary part most. Every
    value returned is a real positive eigenvalue of ``M Delta`` with ``Delta`` in the unit ball of
    the structure, checked to 1e-10: a true lower bound.

    Returns
    -------
    (float, numpy.ndarray)
        The bound (0 when nothing was found) and the diagonal of its ``Delta``.
    """
    from scipy.linalg import matrix_balance
    from scipy.optimize import minimize

    n = M.shape[0]
    nc = n - p
    # a diagonal similarity leaves every eigenvalue of M Delta unchanged (Delta is diagonal) and
    # brings entries 1e5 apart (the two-cart benchmark) to one scale for the optimiser
    _, (scale, _) = matrix_balance(M, permute=False, separate=True)
    M = M * (1.0 / scale)[:, None] * scale[None, :]
    rng = np.random.default_rng(seed)
    given = [start] if np.ndim(start) == 1 else list(start)
    starts = [np.concatenate([np.clip(d[:p].real, -1.0, 1.0), np.minimum(np.abs(d[p:]), 1.0), np.angle(d[p:])]) for d in given]
    starts.append(np.concatenate([np.full(p, 1e-3), np.full(nc, 1e-3), np.zeros(nc)]))
    if p <= SMALL_REAL_STRUCTURE:  # few real blocks: every vertex is a start (the secant then moves one inwards)
        starts += [np.concatenate([np.array(v, dtype=float), np.ones(nc), np.zeros(nc)])
                   for v in itertools.product((-1.0, 1.0), repeat=p)]
    starts += [np.concatenate([rng.uniform(-1.0, 1.0, p), rng.uniform(0.0, 1.0, nc), rng.uniform(-np.pi, np.pi, nc)])
               for _ in range(n_starts)]
    lower, upper = _variable_bounds(p, nc)
    bounds = [(lo if np.isfinite(lo) else None, hi if np.isfinite(hi) else None) for lo, hi in zip(lower, upper)]
    best, best_delta = 0.0, np.zeros(n, dtype=complex)
    for x0 in starts:
        track = _Tracked(M, p)
        track.pick(x0)
        try:
            value, delta = track.exactly_real(x0)  # a nearly real eigenvalue at the start itself
        except np.linalg.LinAlgError:
            value, delta = 0.0, None
        if value > best:
            best, best_delta = value, delta
        track.pick(x0)
        # Im lambda can be tiny everywhere (M nearly real: the two-cart benchmark at 575 rad/s):
        # the constraint is scaled to a unit gradient at the start, or SLSQP sees it as singular
        c = 1.0 / max(float(np.linalg.norm(track.imag_grad(x0))), 1e-300)
        try:
            res = minimize(track.neg_real, x0, jac=True, method="SLSQP", bounds=bounds,
                           constraints=[{"type": "eq", "fun": lambda x: c * track.imag(x), "jac": lambda x: c * track.imag_grad(x)}],
                           options={"maxiter": 60, "ftol": 1e-12})
        except (ValueError, np.linalg.LinAlgError):
            continue
        if not np.all(np.isfinite(res.x)):
            continue
        try:
            value, delta = track.exactly_real(np.clip(res.x, lower, upper))
        except np.linalg.LinAlgError:
            continue
        if value > best:
            best, best_delta = value, delta
    return best, best_delta


def _variable_bounds(p: int, nc: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of ``x = (delta_1..delta_p, r_1..r_c, theta_1..theta_c)``: the unit ball of the structure."""
    return (np.concatenate([-np.ones(p), np.zeros(nc), np.full(nc, -np.inf)]),
            np.concatenate([np.ones(p), np.ones(nc), np.full(nc, np.inf)]))


class _Tracked:
    """One eigenvalue of ``M diag(delta, e^{j theta})`` followed as the variables move."""

    def __init__(self, M: np.ndarray, p: int):
        self.M, self.p = M, p
        self.lam = None

    def delta(self, x: np.ndarray) -> np.ndarray:
        """``x = (delta_1..delta_p, r_1..r_c, theta_1..theta_c)``."""
        nc = (x.size - self.p) // 2
        return np.concatenate([x[: self.p].astype(complex), x[self.p: self.p + nc] * np.exp(1j * x[self.p + nc:])])

    def _eig(self, x: np.ndarray):
        D = self.delta(x)
        lam, X = np.linalg.eig(self.M * D[None, :])
        return lam, X, D

    def pick(self, x: np.ndarray) -> None:
        """Start with the eigenvalue largest towards the positive real axis."""
        lam, _, _ = self._eig(x)
        self.lam = lam[np.argmax(lam.real - 2.0 * np.abs(lam.imag))]

    def _derivs(self, x: np.ndarray):
        lam, X, D = self._eig(x)
        j = int(np.argmin(np.abs(lam - self.lam)))
        self.lam = lam[j]
        xr = X[:, j]
        y = np.conj(np.linalg.inv(X)[j, :])  # left eigenvector: y^* M D = lambda y^*
        c = (np.conj(y) @ self.M) * xr / (np.conj(y) @ xr)  # d lambda / d D_k
        nc = (x.size - self.p) // 2
        phase = np.exp(1j * x[self.p + nc:])
        grad = np.concatenate([c[: self.p], phase * c[self.p:], 1j * D[self.p:] * c[self.p:]])
        return lam[j], grad

    def neg_real(self, x: np.ndarray):
        lam, grad = self._derivs(x)
        return -float(lam.real), -grad.real

    def imag(self, x: np.ndarray) -> float:
        return float(self._derivs(x)[0].imag)

    def imag_grad(self, x: np.ndarray) -> np.ndarray:
        return self._derivs(x)[1].imag

    def exactly_real(self, x: np.ndarray):
        """Make the tracked eigenvalue exactly real by a secant on one variable: of those whose
        Newton step for ``Im lambda = 0`` stays inside its bounds (a real block or a magnitude at
        +-1 may move inwards), the one with the largest effect. ``(lambda, Delta)``, or
        ``(0, Delta)`` when no variable makes it real to 1e-10."""
        nc = (x.size - self.p) // 2
        lo, hi = _variable_bounds(self.p, nc)
        lam, grad = self._derivs(x)
        start = self.lam
        g = grad.imag
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = np.where(g != 0.0, x - lam.imag / g, np.nan)
        inside = np.isfinite(newton) & (newton >= lo) & (newton <= hi)
        for i in np.argsort(-np.abs(g)):
            if not inside[i]:
                continue
            self.lam = start
            value, D = self._secant(x, i, newton[i], lo[i], hi[i])
            if value > 0.0:
                return value, D
        return 0.0, self.delta(x)

    def _secant(self, x: np.ndarray, i: int, first: float, lo: float, hi: float):
        x0, x1 = x.copy(), x.copy()
        f0 = self._derivs(x0)[0].imag
        x1[i] = first
        for _ in range(40):
            lam1 = self._derivs(x1)[0]
            f1 = lam1.imag
            if abs(f1) <= 1e-13 * max(abs(lam1), 1e-300) or f1 == f0:
                break
            with np.errstate(all="ignore"):
                nxt = x1[i] - f1 * (x1[i] - x0[i]) / (f1 - f0)
            if not np.isfinite(nxt):
                break
            x0, f0 = x1.copy(), f1
            x1[i] = min(max(nxt, lo), hi)
        lam_all = np.linalg.eigvals(self.M * self.delta(x1)[None, :])
        D = self.delta(x1)
        ok = (np.abs(lam_all.imag) <= 1e-10 * np.maximum(np.abs(lam_all), 1e-300)) & (lam_all.real > 0.0)
        if not ok.any() or np.any(np.abs(D) > 1.0 + 1e-15):
            return 0.0, D
        return float(np.max(lam_all.real[ok])), D


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
