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
(``lambda_max <= f_tau <= lambda_max + tau log n``). Its gradient (Theorem 4.2 applied to each
eigenvalue, weighted by its softmax weight) and its exact Hessian (divided differences of the
softmax over the eigen-decomposition plus ``trace(W d^2 H)``) come from one Hermitian eigen
decomposition per frequency; damped Newton steps follow ``tau`` down to ``tol`` times the value
(a path-following scheme, as in interior-point methods). The infimum of eq. (2.15) is often
approached along a ray (``d_k -> 0``, ``|g_k| -> inf`` for a real block, where Assumption 4.1
fails); accepted steps are therefore extrapolated (x2, x4, ...) while the value keeps falling.
The start is the Perron-Frobenius ``D`` of ``|M|`` with ``G = 0``. Each matrix is first normalised
by its largest singular value so one set of tolerances fits every frequency.

The certificate in the form of Lemma 2.1 (eq. 2.16, and of SLICOT AB13MD) is
``M^* D_L M + j (G_L M - M^* G_L) <= beta^2 D_L`` with ``D_L = D^2`` and ``G_L = D^2 G``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


Y_LIMIT = 12.0
_TRIAL_STEPS = np.array([1.0, 3.0, 10.0, 30.0, 0.4, 0.1])  # |log d_k| bound for the extrapolated steps (keeps H well scaled)


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
        The upper bound ``sqrt(lambda_max(H) + margin)`` at the returned scalings, the margin
        (:func:`rounding_margin`) covering the eigensolver's rounding.
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


def rounding_margin(H: np.ndarray) -> np.ndarray:
    """Bound on the rounding error of a computed eigenvalue of Hermitian ``H``: ``2 n eps ||H||_F``.

    A backward-stable Hermitian eigensolver returns the eigenvalues of ``H + E`` with
    ``||E||_2 <= p(n) eps ||H||_2`` (Weyl: each eigenvalue moves by at most ``||E||_2``). Near a ray
    optimum (``d_k -> 0``, ``|g_k| -> inf``) ``||H||`` can exceed ``lambda_max`` by 1e10, so the
    margin matters there and is added to every reported ``beta^2``: the bound stays rigorous.
    """
    n = H.shape[-1]
    return 2.0 * n * np.finfo(float).eps * np.linalg.norm(H, axis=(-2, -1))


def bound_at_scalings(M: np.ndarray, d: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``sqrt(lambda_max(H) + margin)`` for given scalings: a valid mu upper bound for any ``d > 0``,
    real ``g`` (the margin of :func:`rounding_margin` covers the eigensolver's rounding)."""
    H = scaled_hermitian(M, d, g)
    lam = np.linalg.eigvalsh(H)[..., -1] + rounding_margin(H)
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

    def __init__(self, M: np.ndarray, structure: MuStructure, param_h: bool = False):
        self.M = M
        self.n = M.shape[-1]
        self.p = structure.n_real
        self.ny = self.n - 1
        self.param_h = param_h

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x = (y_2..y_n, h_1..h_p)`` -> ``(d, g)`` with ``d = exp(y)``, ``g = h / d^2``.

        ``h = D^2 G`` is the ``G`` of the Lemma 2.1 form (eq. 2.16): it stays bounded where the
        optimal ``g`` of eq. (2.15) runs off along ``d_k -> 0``, which keeps Newton's steps short.
        """
        K = x.shape[0]
        y = np.concatenate([np.zeros((K, 1)), x[:, : self.ny]], axis=1)
        g = np.zeros((K, self.n))
        h = x[:, self.ny :]
        g[:, : self.p] = h * np.exp(-2.0 * y[:, : self.p]) if self.param_h else h
        return np.exp(y), g

    def eig(self, x: np.ndarray, idx: np.ndarray):
        """Eigen-decomposition of ``H`` and the certified top (``lambda_max + rounding margin``)."""
        d, g = self.unpack(x)
        M = self.M[idx]
        MD = M * (d[:, :, None] / d[:, None, :])
        GM = g[:, :, None] * MD
        H = np.conj(np.swapaxes(MD, -1, -2)) @ MD + 1j * (GM - np.conj(np.swapaxes(GM, -1, -2)))
        lam, U = np.linalg.eigh(H)
        return lam, U, MD, g, lam[:, -1] + rounding_margin(H)

    def value(self, x, idx, tau):
        """Smoothed value (for the line search) and certified top (for the best iterate)."""
        H = scaled_hermitian(self.M[idx], *self.unpack(x))
        lam = np.linalg.eigvalsh(H)
        top = lam[:, -1]
        f = top + tau * np.log(np.exp((lam - top[:, None]) / tau[:, None]).sum(axis=1))
        return f, top + rounding_margin(H)


def mixed_mu_upper(
    M: np.ndarray,
    structure: MuStructure,
    tol: float = 1e-7,
    max_iter: int = 400,
    variables: str = "both",
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
        Cap on Newton iterations (per run).
    variables : {"both", "g", "h"}
        ``"g"``: optimise over ``(log d, g)`` of eq. (2.15); ``"h"``: over ``(log d, d^2 g)``, the
        ``G`` of eq. (2.16); ``"both"`` (default): a ``"g"`` run with a third of the iterations,
        continued in ``"h"`` variables, which reaches optima on the boundary ``D_L,k -> 0``.

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
    if variables not in ("g", "h", "both"):
        raise ValueError(f"variables: expected 'g', 'h' or 'both', found {variables!r}")
    prob = _Problem(Mn, structure, param_h=(variables == "h"))
    nv = prob.ny + prob.p
    x = np.concatenate([_perron_start(Mn)[:, 1:], np.zeros((K, prob.p))], axis=1)
    if nv > 0:
        x = _newton(prob, x, tol, max_iter if variables != "both" else max(max_iter // 3, 1))
        if variables == "both" and prob.p:
            # continue in (y, h = d^2 g) from where the (y, g) run stopped: it reaches the
            # boundary optima D_L,k -> 0 with G_L finite (eq. 2.16) that the (y, g) run only
            # creeps towards along a ray. Never worse than its start (best value is kept).
            prob_h = _Problem(Mn, structure, param_h=True)
            dg, gg = prob.unpack(x)
            xh0 = np.concatenate([np.log(dg[:, 1:]), (gg * dg**2)[:, : prob.p]], axis=1)
            xh = _newton(prob_h, xh0, tol, max_iter, tau0_rel=1e-3)
            dh, gh = prob_h.unpack(xh)
            x = np.concatenate([np.log(dh[:, 1:]), gh[:, : prob.p]], axis=1)
    d, g = prob.unpack(x)
    lam, U, _, _, top_cert = prob.eig(x, np.arange(K))
    lam = lam[:, ::-1] * (scale**2)[:, None]
    U = U[:, :, ::-1]
    beta = np.sqrt(np.maximum(top_cert * scale**2, 0.0))
    g = g * scale[:, None]
    return MixedMuBound(beta=beta, d=d, g=g, eigenvalues=lam, eigenvectors=U)


def _smoothed_derivatives(prob: _Problem, x: np.ndarray, idx: np.ndarray, tau: np.ndarray, hessian: bool = True):
    """Value, gradient and exact Hessian of ``f_tau = tau log sum exp(lambda_i / tau)``.

    The first-order part uses the divided differences of the softmax weights over the
    eigen-decomposition (Daleckii-Krein); the second-order part is ``trace(W d^2 H)`` with the
    softmax matrix ``W = U diag(w) U^*``.
    """
    lam, U, MD, g, top_cert = prob.eig(x, idx)
    n, p = lam.shape[1], prob.p
    top = lam[:, -1]
    e = np.exp((lam - top[:, None]) / tau[:, None])
    s = e.sum(axis=1)
    f = top + tau * np.log(s)
    w = e / s[:, None]
    # Only the rows i of the r eigenvalues with non-negligible softmax weight are needed: the
    # gradient weights E_a[i, i] by w_i, and the divided differences vanish when both w_i, w_j do.
    r = int(max(1, (w > 1e-15).sum(axis=1).max()))
    E = _eigen_derivatives(U, MD, g, p, r)
    diagE = E[:, :, np.arange(r), np.arange(n - r, n)].real  # E_a[i, i], i in the top r
    grad_yg = (diagE * w[:, None, n - r:]).sum(axis=2)
    # chain rule to x = (y, h), g_k = h_k exp(-2 y_k)
    ny, nv = n - 1, n - 1 + p
    e2 = np.exp(-2.0 * np.log(prob.unpack(x)[0][:, :p]))  # exp(-2 y_k), k < p
    J = np.broadcast_to(np.eye(nv), (lam.shape[0], nv, nv)).copy()
    kk = np.arange(1, p)
    if prob.param_h:
        J[:, ny + kk, kk - 1] = -2.0 * g[:, kk]
        J[:, ny + np.arange(p), ny + np.arange(p)] = e2
        grad = np.einsum("kij,ki->kj", J, grad_yg)
    else:
        grad = grad_yg
    if not hessian:
        return f, top_cert, grad, None
    Hs = _softmax_curvature(lam, w, tau, E, r, grad_yg) + _scaling_curvature(U, w, MD, g, p)
    if not prob.param_h:
        return f, top_cert, grad, 0.5 * (Hs + np.swapaxes(Hs, 1, 2))
    Hs = np.swapaxes(J, 1, 2) @ Hs @ J
    fg = grad_yg[:, ny:]
    Hs[:, kk - 1, kk - 1] += 4.0 * fg[:, kk] * g[:, kk]
    Hs[:, kk - 1, ny + kk] += -2.0 * fg[:, kk] * e2[:, kk]
    Hs[:, ny + kk, kk - 1] += -2.0 * fg[:, kk] * e2[:, kk]
    return f, top_cert, grad, 0.5 * (Hs + np.swapaxes(Hs, 1, 2))


def _eigen_derivatives(U: np.ndarray, MD: np.ndarray, g: np.ndarray, p: int, r: int) -> np.ndarray:
    """``E[:, a, i, j] = (U^* (dH / dx_a) U)[i, j]`` for every variable ``a``, ``i`` among the top
    ``r`` eigenvalues and every ``j``: ``E_a = X_a + X_a^*`` with rank-one-sum ``X_a`` built from
    rows k of U, V = M_D U, W = M_D^* V, Z = M_D^* G U (y_k) and of U, V (g_k)."""
    K, n = U.shape[0], U.shape[-1]
    MDh = np.conj(np.swapaxes(MD, -1, -2))
    V = MD @ U
    W = MDh @ V
    Z = MDh @ (g[:, :, None] * U)
    Uc = np.conj(U)
    A = slice(n - r, n)
    a = np.conj(V) + 1j * g[:, :, None] * Uc
    b = np.conj(W) + 1j * np.conj(Z)
    E = np.empty((K, n - 1 + p, r, n), dtype=complex)
    aA, bA, UA, VA = a[:, 1:, A], b[:, 1:, A], U[:, 1:, A], V[:, 1:, A]
    E[:, : n - 1] = (
        aA[:, :, :, None] * V[:, 1:, None, :]
        - bA[:, :, :, None] * U[:, 1:, None, :]
        + np.conj(a[:, 1:, None, :] * VA[:, :, :, None] - b[:, 1:, None, :] * UA[:, :, :, None])
    )
    E[:, n - 1 :] = 1j * (Uc[:, :p, A][:, :, :, None] * V[:, :p, None, :]) + np.conj(
        1j * Uc[:, :p, None, :] * V[:, :p, A][:, :, :, None]
    )
    return E


def _softmax_curvature(lam: np.ndarray, w: np.ndarray, tau: np.ndarray, E: np.ndarray, r: int, grad_yg: np.ndarray) -> np.ndarray:
    """The Hessian's first part: the divided differences of the softmax weights,
    ``Gamma_ij = (w_i - w_j) / (lambda_i - lambda_j)``, over the eigenvector derivatives."""
    K, n = lam.shape
    nv = E.shape[1]
    dl = lam[:, :, None] - lam[:, None, :]
    adl = np.abs(dl)
    whi = np.where(dl >= 0, w[:, :, None], w[:, None, :])
    t = tau[:, None, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        Gam = np.where(adl > 1e-12 * t, whi * (-np.expm1(-adl / t)) / np.where(adl > 0, adl, 1.0), whi / t)
    # sum over pairs (i, j) with i in the top r: (i, j) and (j, i) both counted when j is not
    GamA = Gam[:, n - r:, :].copy()
    GamA[:, :, : n - r] *= 2.0
    Er = np.concatenate([E.real.reshape(K, nv, r * n), E.imag.reshape(K, nv, r * n)], axis=2)
    G2 = np.concatenate([GamA.reshape(K, 1, r * n)] * 2, axis=2)
    H1 = Er @ np.swapaxes(Er * G2, 1, 2)
    H1 -= grad_yg[:, :, None] * grad_yg[:, None, :] / tau[:, None, None]
    return H1


def _scaling_curvature(U: np.ndarray, w: np.ndarray, MD: np.ndarray, g: np.ndarray, p: int) -> np.ndarray:
    """The Hessian's second part: ``trace(Ws d^2 H)`` with the softmax matrix ``Ws = U diag(w) U^*``."""
    K, n = U.shape[0], U.shape[-1]
    MDh = np.conj(np.swapaxes(MD, -1, -2))
    Ws = (U * w[:, None, :]) @ np.conj(np.swapaxes(U, -1, -2))
    Ws = 0.5 * (Ws + np.conj(np.swapaxes(Ws, -1, -2)))
    eye = np.eye(n)

    def phi(P):
        return (P.sum(axis=2) + P.sum(axis=1))[:, :, None] * eye - P - np.swapaxes(P, 1, 2)

    Q = Ws @ MDh
    P1 = np.swapaxes(Q, 1, 2) * MD
    P2 = np.swapaxes(Ws, 1, 2) * g[:, :, None] * MD
    # trace(C_l Ws C_k^*) with C_l = dM_D / dy_l = e_l M_D[l, :] - M_D[:, l] e_l^T, in n x n products
    MWs = MD @ Ws
    MDt = np.swapaxes(MD, 1, 2)
    Tb = (
        np.einsum("kij,kij->ki", MWs, np.conj(MD))[:, :, None] * eye
        - MDt * Q
        - np.conj(MD) * MWs
        + np.swapaxes(MDh @ MD, 1, 2) * Ws
    )
    Hyy = 2.0 * np.real(phi(P1)) + 2.0 * np.real(Tb) - 2.0 * np.imag(phi(P2))
    Hyg = -2.0 * np.imag(np.diagonal(MWs, axis1=1, axis2=2)[:, :, None] * eye - np.swapaxes(MD, 1, 2) * Ws)
    ny, nv = n - 1, n - 1 + p
    H2 = np.zeros((K, nv, nv))
    H2[:, :ny, :ny] = Hyy[:, 1:, 1:]
    H2[:, :ny, ny:] = Hyg[:, 1:, :p]
    H2[:, ny:, :ny] = np.swapaxes(Hyg[:, 1:, :p], 1, 2)
    return H2


def _newton_direction(Hs: np.ndarray, gr: np.ndarray) -> np.ndarray:
    """``-H^{-1} g`` with ``H`` made positive definite (Cholesky when it already is, else
    eigenvalues floored at 1e-10 of the largest)."""
    scale = np.maximum(np.abs(Hs).max(axis=(1, 2)), 1e-300)
    try:
        L = np.linalg.cholesky(Hs + 1e-12 * scale[:, None, None] * np.eye(Hs.shape[1]))
        if np.all(np.isfinite(L)) and np.all(np.diagonal(L, axis1=1, axis2=2) > 1e-7 * np.sqrt(scale)[:, None]):
            z = np.linalg.solve(L, gr[:, :, None])
            return -np.linalg.solve(np.swapaxes(L, 1, 2), z)[:, :, 0]
    except np.linalg.LinAlgError:
        pass
    ev, evec = np.linalg.eigh(Hs)
    sc = np.maximum(np.abs(ev).max(axis=1), 1e-300)
    ev = np.maximum(ev, 1e-10 * sc[:, None]) + 1e-12 * sc[:, None]
    return -(evec @ ((np.swapaxes(evec, 1, 2) @ gr[:, :, None])[:, :, 0] / ev)[:, :, None])[:, :, 0]


def _newton(prob: _Problem, x: np.ndarray, tol: float, max_iter: int, tau0_rel: float = 0.05) -> np.ndarray:
    """Damped Newton on the smoothed ``lambda_max`` while ``tau`` follows a path down to ``tol``."""
    K, nv = x.shape
    allidx = np.arange(K)
    _, top0, _, _ = _smoothed_derivatives(prob, x, allidx, np.ones(K), hessian=False)
    tau = np.maximum(tau0_rel, tol) * np.maximum(top0, 1e-12)
    best_x, best_top = x.copy(), top0.copy()
    active = np.ones(K, dtype=bool)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        xa, ta = x[idx], tau[idx]
        f, top, gr, Hs = _smoothed_derivatives(prob, xa, idx, ta)
        dirn = _newton_direction(Hs, gr)
        dec = -(dirn * gr).sum(axis=1)  # Newton decrement squared
        ymax = np.abs(dirn[:, : prob.ny]).max(axis=1) if prob.ny else np.zeros(idx.size)
        dirn *= np.minimum(1.0, 4.0 / np.maximum(ymax, 1e-300))[:, None]  # keep exp(y) finite
        slope = (dirn * gr).sum(axis=1)
        # one batched evaluation of several step lengths: the Newton step, its extrapolations
        # along the ray and two backtracks; Armijo decides
        steps = _TRIAL_STEPS
        S = steps.size
        xt = xa[:, None, :] + steps[None, :, None] * dirn[:, None, :]
        with np.errstate(all="ignore"):
            ft, tt = prob.value(xt.reshape(-1, nv), np.repeat(idx, S), np.repeat(ta, S))
        ft, tt = ft.reshape(-1, S), tt.reshape(-1, S)
        ok = np.isfinite(ft) & (ft <= f[:, None] + 1e-4 * steps[None, :] * slope[:, None])
        if prob.ny:
            ok &= (np.abs(xt[:, :, : prob.ny]).max(axis=2) < Y_LIMIT) | (steps[None, :] <= 1.0)
        score = np.where(ok, ft, np.inf)
        pick = np.argmin(score, axis=1)
        rows = np.arange(idx.size)
        todo = ~ok[rows, pick]
        step = np.where(todo, steps.min(), steps[pick])
        xn = xt[rows, pick].copy()
        fn, topn = ft[rows, pick].copy(), tt[rows, pick].copy()
        for _ls in range(6):  # then give up: at a (numerically) converged point
            if not np.any(todo):
                break
            step[todo] *= 0.25
            tq = np.flatnonzero(todo)
            xn[tq] = xa[tq] + step[tq, None] * dirn[tq]
            fn[tq], topn[tq] = prob.value(xn[tq], idx[tq], ta[tq])
            todo[tq] = ~(fn[tq] <= f[tq] + 1e-4 * step[tq] * slope[tq])
        failed = todo  # no decrease found: treat the stage as converged
        xn[failed] = xa[failed]
        topn[failed] = top[failed]
        x[idx] = xn
        improved = topn < best_top[idx]
        best_top[idx[improved]] = topn[improved]
        best_x[idx[improved]] = xn[improved]
        # stage converged when the decrement is small against tau; then shrink tau
        conv = (dec <= 1e-2 * ta) | failed
        c = idx[conv]
        final = c[tau[c] <= tol * np.maximum(best_top[c], 1e-300) * 1.0001]
        active[final] = False
        nxt = c[tau[c] > tol * np.maximum(best_top[c], 1e-300) * 1.0001]
        tau[nxt] = np.maximum(0.1 * tau[nxt], tol * best_top[nxt])
    return best_x
