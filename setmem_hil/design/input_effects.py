"""Effect of a candidate input on the parameter intervals (thesis section 4.3, eq. 4.46-4.53).

For a unit sinusoid at ``omega`` we estimate, without solving any conic program, the interval
each parameter would have after adding that measurement:

* **Certainty equivalence** (eq. 4.53): the measurement is taken to be the midpoint model's
  noise-free response. For the one-mode problem of mode ``i`` (eq. 3.11) the data are then
  ``g_i = g_hat_i(j omega)`` exactly (the other modes' midpoint responses are subtracted), and
  the effective bound is ``E_i = R(omega) + sum_{k != i} max |g_hat_k - g_k|`` (Lemma 3.1), with
  ``R`` the total error bound the experiment will report at ``omega``.
* **Line intersection** (eq. 4.47-4.52): the new point's constraint (eq. 3.26) is
  ``|r0 + J x| <= C`` with ``x = (a1, a0, b1, b0)``, ``r0 = -omega^2 g_i``,
  ``J = [j omega g_i, g_i, -j omega, -1]`` and ``C = max_{a0} |-omega^2 + a1_hi j omega + a0| E_i``
  (the ellipsoid ``x^T Q x <= C^2`` of eq. 3.27/4.49). For the bound of parameter ``j`` attained
  at the stored optimiser ``x*`` of the previous conic solve, all components but ``j`` are held
  at ``x*`` (eq. 4.48) and ``|c + J_j t|^2 = C^2`` (eq. 4.52) is solved for ``t``; with roots
  ``t1 <= t2`` the new upper bound is ``min(t2, upper)`` and the new lower bound
  ``max(t1, lower)``.

When the line misses the ellipsoid altogether (negative discriminant) the thesis is silent; we
take both roots at the vertex ``t = -Re(conj(J_j) c) / |J_j|^2`` (the point of the line closest
to the constraint set), which is continuous with the tangent case.

The same geometry gives the *closeness* of section 5.4.2: ``|r(x_b)| / C`` at the point
``x_b`` of the line where the current bound is attained. Above 1 the new point cuts the
bound; just below 1 a small noise realisation would cut it.

Everything is vectorised over candidates, modes, parameters and the two sides of each
interval; nothing here solves an optimisation problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.model.modal_model import A0, A1, IntervalModel, modal_response

from setmem_hil.identification.embedding import embedding_bound
from setmem_hil.identification.mode_mismatch import mode_mismatch_bounds

_TINY = 1e-300


@dataclass(frozen=True)
class InputEffects:
    """Predicted intervals after each candidate input (eq. 4.52 with eq. 4.53).

    Attributes
    ----------
    omega_rad_s : numpy.ndarray
        Candidate frequencies, shape ``(N,)``.
    lower, upper : numpy.ndarray
        Predicted bounds, shape ``(N, n_modes, 4)``; never outside the current bounds.
    closeness : numpy.ndarray
        ``|r(x_b)| / C`` per candidate, mode, parameter and side (0 lower, 1 upper), shape
        ``(N, n_modes, 4, 2)``; NaN for fixed parameters (section 5.4.2).
    effective_bound : numpy.ndarray
        ``E_i(omega)`` used for each mode, shape ``(n_modes, N)`` (eq. 3.11).
    """

    omega_rad_s: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    closeness: np.ndarray
    effective_bound: np.ndarray

    @property
    def width(self) -> np.ndarray:
        """Predicted widths ``delta`` after each candidate, shape ``(N, n_modes, 4)``."""
        return self.upper - self.lower


def certainty_equivalent_response(model: IntervalModel, omega_rad_s) -> np.ndarray:
    """Noise-free per-mode response of the midpoint model, shape ``(n_modes, N)`` (eq. 4.53)."""
    return modal_response(model.midpoint.values, omega_rad_s)


def effective_bounds(model: IntervalModel, omega_rad_s, noise_bound) -> np.ndarray:
    """``E_i(omega) = R(omega) + sum_{k != i} max |g_hat_k - g_k|`` (eq. 3.11, Lemma 3.1).

    Parameters
    ----------
    model : IntervalModel
        Current parameter box.
    omega_rad_s : array_like
        Frequencies, shape ``(N,)``.
    noise_bound : array_like
        Total error bound ``R(omega)`` the experiment will report there, shape ``(N,)``.

    Returns
    -------
    numpy.ndarray
        Shape ``(n_modes, N)``; ``inf`` where another mode's box allows a pole on the axis.
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    R = np.broadcast_to(np.asarray(noise_bound, dtype=float), w.shape)
    mismatch = mode_mismatch_bounds(model, w)  # (n_modes, N)
    with np.errstate(invalid="ignore"):
        others = mismatch.sum(axis=0, keepdims=True) - mismatch
    # inf - inf for the mode that is itself unbounded: recompute those columns directly
    bad = ~np.isfinite(others)
    if np.any(bad):
        n = model.n_modes
        for i in range(n):
            if np.any(bad[i]):
                others[i] = np.sum(np.delete(mismatch, i, axis=0), axis=0) if n > 1 else 0.0
    return R[None, :] + others


def _clean_optimizers(optimizers: np.ndarray, model: IntervalModel) -> np.ndarray:
    """Replace NaN components of the stored optimisers by the midpoint (fixed parameters)."""
    opt = np.array(optimizers, dtype=float, copy=True)
    if opt.shape != (model.n_modes, 4, 2, 4):
        raise ValueError(f"optimizers: expected shape ({model.n_modes}, 4, 2, 4), found {opt.shape}")
    mid = model.midpoint.values[:, None, None, :]
    return np.where(np.isnan(opt), np.broadcast_to(mid, opt.shape), opt)


def estimate_input_effects(
    model: IntervalModel,
    optimizers: np.ndarray,
    omega_rad_s,
    noise_bound,
) -> InputEffects:
    """Predicted intervals after measuring at each candidate (eq. 4.47-4.53), vectorised.

    Parameters
    ----------
    model : IntervalModel
        Current bounds (``lower``, ``upper`` of shape ``(n_modes, 4)``).
    optimizers : numpy.ndarray
        ``(n_modes, 4, 2, 4)``: the parameter vector at which the lower (``[..., 0, :]``) and
        upper (``[..., 1, :]``) bound of each parameter was attained in the last conic solve
        (:attr:`setmem_hil.identification.algorithm.IdentificationResult.optimizers`); NaN rows for fixed
        parameters.
    omega_rad_s : array_like
        Candidate frequencies, shape ``(N,)``.
    noise_bound : array_like
        Total error bound ``R(omega)`` expected at each candidate, shape ``(N,)``.

    Returns
    -------
    InputEffects

    Examples
    --------
    >>> import numpy as np
    >>> from setmem_hil.model.modal_model import IntervalModel
    >>> box = IntervalModel([[0.0, 0.8, 0.0, 3.0]], [[0.1, 1.2, 0.0, 5.0]])
    >>> opt = np.tile(box.midpoint.values[:, None, None, :], (1, 4, 2, 1))
    >>> eff = estimate_input_effects(box, opt, [1.0], [0.05])
    >>> bool(np.all(eff.width <= box.width))
    True
    """
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    R = np.broadcast_to(np.asarray(noise_bound, dtype=float), w.shape)
    n_modes = model.n_modes
    lo = model.lower
    hi = model.upper
    opt = _clean_optimizers(optimizers, model)
    fixed_rows = np.all(np.isnan(np.asarray(optimizers, dtype=float)), axis=-1)  # (n_modes, 4, 2)
    fixed_rows |= model.fixed[:, :, None]

    E = effective_bounds(model, w, R)  # (n_modes, N)
    C = embedding_bound(w[None, :], E, lo[:, A0, None], hi[:, A0, None], hi[:, A1, None])  # (n_modes, N)
    g = certainty_equivalent_response(model, w)  # (n_modes, N)

    jw = 1j * w[None, :]
    # J[i, n, p]: the affine map of eq. 3.26 for mode i at candidate n
    J = np.stack([jw * g, g, np.broadcast_to(-jw, g.shape), -np.ones_like(g)], axis=-1)  # (m, N, 4)
    r0 = -(w[None, :] ** 2) * g  # (m, N)

    # residual at each optimiser: r(x*) = r0 + J x*, for (mode, param j, side s)
    Jx = np.einsum("mnp,mjsp->mnjs", J, opt)
    r_star = r0[:, :, None, None] + Jx  # (m, N, 4, 2)
    Jj = J[:, :, :, None]  # (m, N, 4, 1): J_j for parameter j
    xj = np.transpose(np.diagonal(opt, axis1=1, axis2=3), (0, 2, 1))[:, None, :, :]  # (m, 1, 4, 2): x*_j
    c = r_star - Jj * xj  # c = r0 + sum_{p != j} J_p x*_p
    a = np.abs(Jj) ** 2
    b = 2.0 * np.real(np.conj(Jj) * c)
    Cn = C[:, :, None, None]
    with np.errstate(invalid="ignore", over="ignore"):
        cc = np.abs(c) ** 2 - Cn**2
        disc = b * b - 4.0 * a * cc
    a_safe = np.maximum(a, _TINY)
    vertex = -b / (2.0 * a_safe)
    sq = np.sqrt(np.where(disc > 0, disc, 0.0))
    # numerically stable roots of a t^2 + b t + cc = 0
    q = -0.5 * (b + np.where(b >= 0, 1.0, -1.0) * sq)
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = q / a_safe
        r2 = np.where(np.abs(q) > 0, cc / np.where(np.abs(q) > 0, q, 1.0), vertex)
    t1 = np.where(disc > 0, np.minimum(r1, r2), vertex)
    t2 = np.where(disc > 0, np.maximum(r1, r2), vertex)
    unconstrained = ~np.isfinite(Cn) | ~np.isfinite(t1) | ~np.isfinite(t2)
    t1 = np.where(unconstrained, -np.inf, t1)
    t2 = np.where(unconstrained, np.inf, t2)

    lo_b = lo[:, None, :]  # (m, 1, 4)
    hi_b = hi[:, None, :]
    new_lo = np.clip(np.maximum(t1[..., 0], lo_b), lo_b, hi_b)  # side 0: lower bound's optimiser
    new_hi = np.clip(np.minimum(t2[..., 1], hi_b), lo_b, hi_b)  # side 1: upper bound's optimiser
    fixed_lo = fixed_rows[:, None, :, 0]
    fixed_hi = fixed_rows[:, None, :, 1]
    new_lo = np.where(fixed_lo, lo_b, new_lo)
    new_hi = np.where(fixed_hi, hi_b, new_hi)
    crossed = new_lo > new_hi  # the estimate collapses the interval: width 0 at the mean
    mean = 0.5 * (new_lo + new_hi)
    new_lo = np.where(crossed, mean, new_lo)
    new_hi = np.where(crossed, mean, new_hi)

    # closeness (section 5.4.2): |c + J_j x_b| / C at the current bound x_b
    bound_point = np.stack([np.broadcast_to(lo_b, new_lo.shape), np.broadcast_to(hi_b, new_hi.shape)], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        closeness = np.abs(c + Jj * bound_point) / np.maximum(Cn, _TINY)
    closeness = np.where(unconstrained, 0.0, closeness)
    closeness = np.where(fixed_rows[:, None, :, :], np.nan, closeness)

    return InputEffects(
        omega_rad_s=w,
        lower=np.transpose(new_lo, (1, 0, 2)),
        upper=np.transpose(new_hi, (1, 0, 2)),
        closeness=np.transpose(closeness, (1, 0, 2, 3)),
        effective_bound=E,
    )


__all__ = ["InputEffects", "certainty_equivalent_response", "effective_bounds", "estimate_input_effects"]
