"""Steady-state sine estimation with modelled transients (pure numerics, no I/O).

The sine-dwell measurement needs the complex amplitude (phasor) ``Y`` of a sampled signal at the
known excitation frequency ``omega``, ``y(t) ~ Re(Y e^{j omega t}) + c``, and a covariance of
its estimate, so that the measured ``g(j omega) = Y_response / Y_force`` comes with the bound
``R(j omega)`` of thesis eq. (3.7) that the set-membership identification needs.

* :func:`fit_sine` is the IEEE Std 1057 three-parameter fit (in-phase, quadrature, offset;
  frequency known) by linear least squares, extended with decaying regressors
  ``e^{-sigma_k tau} cos(omega_dk tau)``, ``e^{-sigma_k tau} sin(omega_dk tau)`` for the
  free response of lightly damped modes with poles ``-sigma_k +- j omega_dk`` (the
  homogeneous solution of eq. 2.6). With the transient in the model the fit need not wait
  five time constants (500 s for the beam's first mode) before acquiring.
* :func:`fit_sine_with_transients` finds the poles: starting from estimates (e.g. the current
  model's midpoint, eq. 2.25) it scans each mode's frequency band, keeps a pole only if it
  reduces the residual significantly (F-test), and refines all poles jointly by variable
  projection (nonlinear least squares over the poles with the linear coefficients projected
  out). The phasor covariance is taken from the full Jacobian (linear *and* pole parameters),
  so the uncertainty of the pole estimates is accounted for in the error bound.
* :func:`phasor_ratio` propagates both channels' covariances to ``Y_r / Y_f``;
  :func:`confidence_radius` turns a 2x2 covariance into an absolute bound at a confidence.
* :func:`cramer_rao_phasor_variance`: the Cramer-Rao bound ``2 s^2 / N`` of each phasor
  component of a sinusoid of known frequency in white noise (for the benchmark).

Phasor convention: ``y(t) = Re(Y e^{j omega (t - t_ref)})``, i.e.
``y = Re(Y) cos(omega tau) - Im(Y) sin(omega tau)``, ``tau = t - t_ref``. Both channels of a
dwell must use the same ``t_ref``; their ratio then does not depend on it.

Example
-------
>>> import numpy as np
>>> t = np.arange(640) * (2 * np.pi / 2.0) / 32
>>> y = 3 * np.cos(2.0 * t + 0.5) + 0.01 * np.random.default_rng(0).standard_normal(t.size)
>>> fit = fit_sine(t, y, 2.0)
>>> bool(abs(fit.phasor - 3 * np.exp(0.5j)) < 0.01)
True
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from setmem_hil.numerics.blas_threads import single_thread_blas as _blas1
from setmem_hil.errors import DataQualityError


@dataclass(frozen=True)
class DampedPole:
    """A lightly damped pole pair ``-sigma +- j omega_d`` (free response ``e^{-sigma t} cos``)."""

    sigma_per_s: float
    omega_d_rad_s: float

    @classmethod
    def from_modal(cls, omega_n_rad_s: float, zeta: float) -> "DampedPole":
        """Pole of ``s^2 + 2 zeta omega_n s + omega_n^2`` (eq. 2.1: ``a1 = 2 zeta omega_n``)."""
        z = min(max(float(zeta), 0.0), 0.999)
        return cls(z * omega_n_rad_s, omega_n_rad_s * np.sqrt(1.0 - z * z))


@dataclass(frozen=True)
class PoleSearchBand:
    """Where to look for one mode's transient: a pole estimate and its frequency band."""

    guess: DampedPole
    omega_min_rad_s: float
    omega_max_rad_s: float
    exclude: tuple[tuple[float, float], ...] = ()  # sub-intervals not to scan (other modes' bands)
    # the decay rate's guaranteed range (an identified mode: a1 / 2 within its interval); a pole
    # left free to become undamped at a line's frequency is the line itself, and the fit splits them
    sigma_min_per_s: float = 1e-6
    sigma_max_per_s: float = math.inf


@dataclass(frozen=True)
class SineFit:
    """Result of a sine fit.

    Attributes
    ----------
    phasor : complex
        ``Y`` with ``y ~ Re(Y e^{j omega (t - t_ref)})``.
    covariance : ndarray (2, 2)
        Covariance of ``(Re Y, Im Y)``, including the pole parameters' uncertainty.
    offset : float
        Fitted constant.
    noise_rms : float
        Residual-based noise estimate ``sqrt(RSS / (N - p))``.
    n_samples, n_params : int
        Samples used and parameters fitted (linear + 2 per refined pole).
    poles : tuple of DampedPole
        Transient poles in the final model.
    transient_amplitudes : tuple of float
        Amplitude of each transient at the window start.
    omega_rad_s, t_ref_s : float
    pole_covariance : ndarray (2K, 2K) or None
        Covariance of ``(sigma_1, omega_d1, sigma_2, ...)`` of the refined poles (``None`` when
        no pole was refined); order of ``poles`` restricted to the refined ones.
    pole_sources : tuple of int
        For :func:`fit_sine_with_transients`: index of the search band each pole came from.
    """

    phasor: complex
    covariance: np.ndarray
    offset: float
    noise_rms: float
    n_samples: int
    n_params: int
    poles: tuple[DampedPole, ...]
    transient_amplitudes: tuple[float, ...]
    omega_rad_s: float
    t_ref_s: float
    pole_covariance: np.ndarray | None = None
    pole_sources: tuple[int, ...] = ()
    line_omegas: tuple[float, ...] = ()
    line_phasors: tuple[complex, ...] = ()
    line_covariances: tuple[np.ndarray, ...] = ()

    @property
    def phasor_std(self) -> float:
        """RMS of the phasor error, ``sqrt(trace(covariance))``."""
        return float(np.sqrt(np.trace(self.covariance)))

    @property
    def n_lines(self) -> int:
        """Sinusoids fitted (1 for a sine dwell, more for a multisine record)."""
        return max(1, len(self.line_omegas))

    def line(self, k: int) -> "SineFit":
        """The fit seen as line ``k``'s: its phasor, covariance and frequency in the scalar fields."""
        if not self.line_omegas:
            if k != 0:
                raise IndexError(f"sine fit: line {k} of 1")
            return self
        return dataclasses.replace(self, phasor=self.line_phasors[k], covariance=self.line_covariances[k],
                                   omega_rad_s=self.line_omegas[k])


def _check_signal(t_s, y, omega_rad_s) -> tuple[np.ndarray, np.ndarray]:
    t = np.asarray(t_s, dtype=float).ravel()
    v = np.asarray(y, dtype=float).ravel()
    if t.size != v.size:
        raise DataQualityError(f"sine fit: t_s has {t.size} samples but y has {v.size}")
    if t.size < 8:
        raise DataQualityError(f"sine fit: expected at least 8 samples, found {t.size}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
        raise DataQualityError(f"sine fit: {int(np.sum(~np.isfinite(v)) + np.sum(~np.isfinite(t)))} non-finite samples")
    lines = _lines(omega_rad_s)
    if lines.size == 0 or not (np.all(np.isfinite(lines)) and np.all(lines > 0)):
        raise ValueError(f"sine fit: omega_rad_s must be finite and > 0, found {omega_rad_s!r}")
    return t, v


def _lines(omega) -> np.ndarray:
    """The excitation frequencies: one (a sine) or several (a multisine record)."""
    return np.atleast_1d(np.asarray(omega, dtype=float)).ravel()


def _n_steady(omega) -> int:
    """Columns of the steady state: in-phase and quadrature per line, and the offset."""
    return 2 * _lines(omega).size + 1


def _design(t: np.ndarray, omega, t_ref: float, poles, t_start: float) -> np.ndarray:
    """Columns ``cos, -sin`` per line, the offset, then ``e^{-sigma t} (cos, sin)`` per pole."""
    tau = t - t_ref
    cols = []
    for w in _lines(omega):
        cols += [np.cos(w * tau), -np.sin(w * tau)]
    cols.append(np.ones_like(t))
    ts = t - t_start
    for p in poles:
        env = np.exp(-p.sigma_per_s * ts)
        cols.append(env * np.cos(p.omega_d_rad_s * ts))
        cols.append(env * np.sin(p.omega_d_rad_s * ts))
    return np.column_stack(cols)


def _pole_jacobian_columns(t, poles, coef, t_start, first: int) -> list[np.ndarray]:
    """d(model)/d(sigma_k), d(model)/d(omega_dk) at the fitted linear coefficients (the first
    pole's coefficients at index ``first``, :func:`_n_steady`)."""
    ts = t - t_start
    cols = []
    for k, p in enumerate(poles):
        c, s = coef[first + 2 * k], coef[first + 1 + 2 * k]
        env = np.exp(-p.sigma_per_s * ts)
        cw, sw = np.cos(p.omega_d_rad_s * ts), np.sin(p.omega_d_rad_s * ts)
        cols.append(-ts * env * (c * cw + s * sw))
        cols.append(ts * env * (-c * sw + s * cw))
    return cols


def _solve(X: np.ndarray, v: np.ndarray):
    # column scaling for conditioning; lstsq via SVD
    scale = np.sqrt(np.sum(X * X, axis=0))
    scale[scale == 0] = 1.0
    coef_s, *_ = np.linalg.lstsq(X / scale, v, rcond=None)
    coef = coef_s / scale
    r = v - X @ coef
    return coef, r


@_blas1
def fit_sine(t_s, y, omega_rad_s, poles: tuple[DampedPole, ...] = (), *, t_ref_s: float | None = None,
             refined_poles: bool | tuple[bool, ...] = False,
             pole_prior_covariance: np.ndarray | None = None,
             refined_prior_information: np.ndarray | None = None) -> SineFit:
    """IEEE-1057 three-parameter sine fit plus decaying regressors for known transient poles.

    Parameters
    ----------
    t_s, y : array_like
        Sample times and values (finite; raises DataQualityError otherwise).
    omega_rad_s : float or sequence of float
        Known excitation frequency, or the lines of a multisine record (each gets its phasor
        in ``line_phasors``, ``line_covariances``; ``phasor`` is the first line's). With
        several lines each line's covariance uses the residual's noise level near that line
        (:func:`local_noise_variance`), since the noise need not be white over a broad band.
    poles : tuple of DampedPole
        Transient poles to model (their free responses are fitted with free amplitude/phase).
    t_ref_s : float, optional
        Phase reference time (default ``t_s[0]``).
    refined_poles : bool or tuple of bool
        If the poles (all, or those marked) were estimated from these data, include their two
        parameters each in the covariance (full Jacobian) and in the degrees of freedom.
    pole_prior_covariance : ndarray (2M, 2M), optional
        Covariance of ``(sigma, omega_d)`` of the poles *not* refined (in order), estimated
        independently of these data (e.g. pooled from earlier dwells): their error is
        propagated to the phasor, ``Cov += G P G^T`` with ``G = -X^+ dX/dtheta c`` (the change
        of the linear coefficients when the fixed poles move).
    refined_prior_information : ndarray (2R, 2R), optional
        Prior information (inverse covariance) on the *refined* poles' parameters, added to the
        data's Fisher information ``J^T J / s^2`` (Bayesian combination with earlier dwells).

    Returns
    -------
    SineFit
    """
    t, v = _check_signal(t_s, y, omega_rad_s)
    lines = _lines(omega_rad_s)
    n_lines, first = lines.size, _n_steady(omega_rad_s)
    t_ref = float(t[0]) if t_ref_s is None else float(t_ref_s)
    t_start = float(t[0])
    X = _design(t, omega_rad_s, t_ref, poles, t_start)
    coef, r = _solve(X, v)
    n_lin = X.shape[1]
    mask = tuple(bool(refined_poles) for _ in poles) if isinstance(refined_poles, bool) else tuple(refined_poles)
    if len(mask) != len(poles):
        raise ValueError(f"refined_poles: expected {len(poles)} flags, found {len(mask)}")
    cols = _pole_jacobian_columns(t, poles, coef, t_start, first)
    ref_cols = [c for k, m in enumerate(mask) if m for c in cols[2 * k : 2 * k + 2]]
    fix_cols = [c for k, m in enumerate(mask) if not m for c in cols[2 * k : 2 * k + 2]]
    J = np.column_stack([X] + ref_cols) if ref_cols else X
    p = J.shape[1]
    dof = t.size - p
    if dof < 1:
        raise DataQualityError(f"sine fit: {t.size} samples cannot determine {p} parameters")
    s2 = max(float(r @ r) / dof, 1e-300)
    M = (J.T @ J) / s2  # Fisher information of all estimated parameters
    if refined_prior_information is not None and ref_cols:
        Ip = np.asarray(refined_prior_information, dtype=float)
        if Ip.shape != (len(ref_cols), len(ref_cols)):
            raise ValueError(f"refined_prior_information: expected shape {(len(ref_cols),) * 2}, found {Ip.shape}")
        M[n_lin:, n_lin:] += Ip
    scale = np.sqrt(np.abs(np.diag(M)))
    scale[scale == 0] = 1.0
    try:
        cov = np.linalg.pinv(M / np.outer(scale, scale), rcond=1e-13) / np.outer(scale, scale)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - pinv of a symmetric matrix
        raise DataQualityError(f"sine fit: singular normal matrix at omega {lines[0]:g} rad/s") from exc
    line_cov = [cov[2 * k : 2 * k + 2, 2 * k : 2 * k + 2].copy() for k in range(n_lines)]
    if pole_prior_covariance is not None and fix_cols:
        P = np.asarray(pole_prior_covariance, dtype=float)
        if P.shape != (len(fix_cols), len(fix_cols)):
            raise ValueError(f"pole_prior_covariance: expected shape {(len(fix_cols),) * 2}, found {P.shape}")
        # sensitivity of all estimated parameters to the fixed poles, the lines' rows
        G_all = -(cov @ (J.T @ np.column_stack(fix_cols)) / s2)
        for k in range(n_lines):
            G = G_all[2 * k : 2 * k + 2]
            line_cov[k] = line_cov[k] + G @ P @ G.T
    if n_lines > 1:
        # each line sees the noise near its own frequency, not the broadband average s2
        local = local_noise_variance(t, r * math.sqrt(t.size / dof), lines, tuple(p.omega_d_rad_s for p in poles))
        line_cov = [c * (loc / s2) for c, loc in zip(line_cov, local)]
    pole_cov = cov[n_lin:, n_lin:].copy() if ref_cols else None
    amps = tuple(float(np.hypot(coef[first + 2 * k], coef[first + 1 + 2 * k])) for k in range(len(poles)))
    line_phasors = tuple(complex(coef[2 * k], coef[2 * k + 1]) for k in range(n_lines))
    return SineFit(
        phasor=line_phasors[0],
        covariance=line_cov[0],
        offset=float(coef[2 * n_lines]),
        noise_rms=float(np.sqrt(s2)),
        n_samples=int(t.size),
        n_params=int(p),
        poles=tuple(poles),
        transient_amplitudes=amps,
        omega_rad_s=float(lines[0]),
        t_ref_s=t_ref,
        pole_covariance=pole_cov,
        line_omegas=tuple(float(w) for w in lines) if n_lines > 1 else (),
        line_phasors=line_phasors if n_lines > 1 else (),
        line_covariances=tuple(line_cov) if n_lines > 1 else (),
    )


def local_noise_variance(t, residual, lines, avoid=(), n_bins: int = 24) -> np.ndarray:
    """Noise variance (per sample, white-equivalent) near each line, from the residual's periodogram.

    For white noise of variance ``s^2`` the periodogram ``|DFT(r)_j|^2 / N`` has mean ``s^2``
    at every bin; for coloured noise it is the spectral density, which is what a phasor at
    ``omega_k`` sees. Per line: the mean over the ``n_bins`` bins nearest in log-frequency,
    leaving out DC, Nyquist and the bins within 1.5 bins of any line or ``avoid`` frequency
    (the fitted transients' poles), where the fit has removed part of the noise. ``residual``
    should already be scaled by ``sqrt(N / (N - p))`` (the degrees of freedom the fit used).
    Falls back to ``mean(residual^2)`` when too few bins remain.
    """
    r = np.asarray(residual, dtype=float)
    n = r.size
    dt = float(t[1] - t[0])
    spectrum = np.abs(np.fft.rfft(r)) ** 2 / n
    omega = 2 * np.pi * np.fft.rfftfreq(n, dt)
    step = omega[1]
    eligible = np.ones(omega.size, dtype=bool)
    eligible[0] = False
    if n % 2 == 0:
        eligible[-1] = False
    for w in tuple(np.ravel(lines)) + tuple(avoid):
        eligible &= np.abs(omega - w) > 1.5 * step
    index = np.flatnonzero(eligible)
    fallback = float(np.mean(r * r))
    out = []
    for w in np.ravel(lines):
        if index.size < n_bins:
            out.append(fallback)
            continue
        below, above = index[omega[index] < w][::-1], index[omega[index] > w]
        half = n_bins // 2
        if below.size < half or above.size < half:  # at an edge of the band: the nearest bins
            nearest = index[np.argsort(np.abs(np.log(omega[index] / w)))[:n_bins]]
            out.append(float(np.mean(spectrum[nearest])))
            continue
        # the larger side: a sloping spectrum is not averaged down to below its value at w
        out.append(max(float(np.mean(spectrum[below[:half]])), float(np.mean(spectrum[above[:half]]))))
    return np.array(out)


def _rss(t, v, omega, t_ref, poles, t_start) -> float:
    _, r = _solve(_design(t, omega, t_ref, poles, t_start), v)
    return float(r @ r)


def _scan(t, v, omega, t_ref, poles, t_start, grid, sigmas):
    """Best single extra pole on a (frequency x decay) grid: vectorised projected RSS.

    With ``Q`` an orthonormal basis of the current design and ``r`` its residual, adding the
    two columns ``C`` lowers the RSS by ``r^T C' (C'^T C')^{-1} C'^T r``, ``C' = C - Q Q^T C``.
    """
    X = _design(t, omega, t_ref, poles, t_start)
    Q, _ = np.linalg.qr(X / np.sqrt(np.sum(X * X, axis=0)))
    r = v - Q @ (Q.T @ v)
    rss0 = float(r @ r)
    ts = (t - t_start)[:, None]
    best = (np.inf, None)
    chunks = np.array_split(grid, max(1, grid.size // 64))
    for sg in sigmas:
        env = np.exp(-sg * ts)  # once per decay, not per chunk: a quarter of a long multisine record's fit
        for chunk in chunks:
            phase = ts * chunk[None, :]
            c1 = env * np.cos(phase)
            c2 = env * np.sin(phase)
            c1 = c1 - Q @ (Q.T @ c1)
            c2 = c2 - Q @ (Q.T @ c2)
            a11 = np.sum(c1 * c1, axis=0)
            a22 = np.sum(c2 * c2, axis=0)
            a12 = np.sum(c1 * c2, axis=0)
            b1 = r @ c1
            b2 = r @ c2
            det = a11 * a22 - a12 * a12
            ok = det > 1e-12 * np.maximum(a11 * a22, 1e-300)
            red = np.where(ok, (a22 * b1 * b1 - 2 * a12 * b1 * b2 + a11 * b2 * b2) / np.where(ok, det, 1.0), 0.0)
            k = int(np.argmax(red))
            if rss0 - red[k] < best[0]:
                best = (rss0 - float(red[k]), DampedPole(float(sg), float(chunk[k])))
    return best


def _refine(t, v, omega, t_ref, poles, t_start, bands, fixed=(), priors=None, noise_scale=1.0) -> tuple[DampedPole, ...]:
    """Variable projection: minimise the projected residual over the pole parameters of
    ``poles`` (the ``fixed`` poles stay in the model unchanged).

    ``priors[k]`` = ``(mean (2,), information (2, 2))`` adds the Gaussian prior term
    ``s^2 (x_k - mean)^T I (x_k - mean)`` (``s`` = ``noise_scale``), i.e. the negative log
    posterior up to a constant.
    """
    fixed = tuple(fixed)
    priors = list(priors) if priors is not None else [None] * len(poles)
    prior_rows = []
    for k, pr in enumerate(priors):
        if pr is not None:
            mean, info = pr
            R = np.linalg.cholesky(np.asarray(info, dtype=float) + 1e-300 * np.eye(2)).T  # info = R^T R
            prior_rows.append((k, np.asarray(mean, dtype=float), noise_scale * R))
    x0 = np.array([q for p in poles for q in (p.sigma_per_s, p.omega_d_rad_s)])
    # bands: (omega_lo, omega_hi[, sigma_lo, sigma_hi]); the decay rate below omega_hi unless bounded tighter
    s_lo = [max(1e-6, b[2]) if len(b) > 2 else 1e-6 for b in bands]
    s_hi = [max(min(max(b[1], 1e-3), b[3]), lo_s + 1e-9) if len(b) > 3 else max(b[1], 1e-3) for b, lo_s in zip(bands, s_lo)]
    lo = np.array([q for b, sl in zip(bands, s_lo) for q in (sl, b[0])])
    hi = np.array([q for b, sh in zip(bands, s_hi) for q in (sh, b[1])])
    x0 = np.clip(x0, lo + 1e-12, hi - 1e-12)

    def unpack(x):
        return tuple(DampedPole(x[2 * k], x[2 * k + 1]) for k in range(len(poles)))

    cache: dict = {}

    def prior_resid(x):
        return [R @ (x[2 * k : 2 * k + 2] - m) for k, m, R in prior_rows]

    def resid(x):
        ps = fixed + unpack(x)
        X = _design(t, omega, t_ref, ps, t_start)
        coef, r = _solve(X, v)
        cache["last"] = (x.copy(), X, coef)
        return np.concatenate([r] + prior_resid(x)) if prior_rows else r

    def jac(x):
        # Kaufman's variable-projection Jacobian: -(I - P_X) dX/dtheta c
        last = cache.get("last")
        if last is None or not np.array_equal(last[0], x):
            resid(x)
            last = cache["last"]
        _, X, coef = last
        Jp = np.column_stack(_pole_jacobian_columns(t, fixed + unpack(x), coef, t_start, _n_steady(omega))[2 * len(fixed) :])
        Q, _ = np.linalg.qr(X / np.sqrt(np.sum(X * X, axis=0)))
        Jd = -(Jp - Q @ (Q.T @ Jp))
        if not prior_rows:
            return Jd
        rows = []
        for k, _, R in prior_rows:
            block = np.zeros((2, x.size))
            block[:, 2 * k : 2 * k + 2] = R
            rows.append(block)
        return np.vstack([Jd] + rows)

    sol = least_squares(resid, x0, jac=jac, bounds=(lo, hi), x_scale="jac", max_nfev=40, xtol=1e-10, ftol=1e-12)
    x = sol.x
    return tuple(DampedPole(float(x[2 * k]), float(x[2 * k + 1])) for k in range(len(poles)))


@_blas1
def fit_sine_with_transients(t_s, y, omega_rad_s, bands: tuple[PoleSearchBand, ...] = (), *,
                             t_ref_s: float | None = None, significance: float = 25.0,
                             max_poles: int = 4, fixed_poles: tuple[DampedPole, ...] = (),
                             fixed_covariance: np.ndarray | None = None,
                             pole_priors: dict | None = None) -> SineFit:
    """Sine fit whose transient poles are found from estimates and refined on the data.

    For each band (in order) the mode's damped frequency is scanned on a grid of resolution
    ``pi / T`` over the band and a few decay rates around the estimate; the best candidate
    is kept if it lowers the residual sum of squares by more than ``significance`` times the
    noise variance (a likelihood-ratio / F-test with 2 extra parameters; 25 is far beyond
    chance for Gaussian noise), then all kept poles are refined jointly by variable projection
    within their bands. The phasor covariance includes the pole parameters (full Jacobian).

    Parameters
    ----------
    t_s, y : array_like
    omega_rad_s : float
    bands : tuple of PoleSearchBand
        Pole estimates and the frequency bands to search (e.g. from an IntervalModel).
    t_ref_s : float, optional
    significance : float
        Residual reduction, in units of the noise variance, needed to add a pole.
    max_poles : int
    fixed_poles : tuple of DampedPole
        Poles known from elsewhere (kept in the model, not refined; listed first in the result).
    fixed_covariance : ndarray (2M, 2M), optional
        Their covariance, propagated to the phasor (see :func:`fit_sine`).
    pole_priors : dict, optional
        ``{band index: (DampedPole, covariance (2, 2))}``: a Gaussian prior on that band's pole
        (e.g. the posterior of earlier dwells). The band is then not scanned: its pole starts
        at the prior mean, is refined with the prior term, and the returned
        ``pole_covariance`` is the posterior one (data and prior information combined).

    Returns
    -------
    SineFit
    """
    t, v = _check_signal(t_s, y, omega_rad_s)
    t_ref = float(t[0]) if t_ref_s is None else float(t_ref_s)
    t_start = float(t[0])
    T = float(t[-1] - t[0])
    if T <= 0:
        raise DataQualityError("sine fit: samples span no time")
    kept: list[DampedPole] = []
    kept_bands: list[tuple[float, float, float, float]] = []
    kept_idx: list[int] = []
    fixed = tuple(fixed_poles)
    rss = _rss(t, v, omega_rad_s, t_ref, fixed, t_start)
    pole_priors = dict(pole_priors or {})
    kept_priors: list = []
    for band_index, band in enumerate(bands):
        if len(kept) >= max_poles:
            break
        if band_index in pole_priors:
            mean_pole, pcov = pole_priors[band_index]
            kept.append(mean_pole)
            lo_w = min(float(band.omega_min_rad_s), mean_pole.omega_d_rad_s)
            hi_w = max(float(band.omega_max_rad_s), mean_pole.omega_d_rad_s)
            kept_bands.append((lo_w, hi_w, band.sigma_min_per_s, band.sigma_max_per_s))
            kept_idx.append(band_index)
            kept_priors.append((np.array([mean_pole.sigma_per_s, mean_pole.omega_d_rad_s]), np.linalg.inv(pcov)))
            rss = _rss(t, v, omega_rad_s, t_ref, fixed + tuple(kept), t_start)
            continue
        w_lo, w_hi = float(band.omega_min_rad_s), float(band.omega_max_rad_s)
        if not (0 < w_lo <= w_hi):
            continue
        step = np.pi / T
        grid = np.arange(w_lo, w_hi + step, step) if w_hi > w_lo else np.array([w_lo])
        if grid.size > 400:
            grid = np.linspace(w_lo, w_hi, 400)
        # The band's own estimate belongs on the grid: a grid point a fraction of pi/T away from
        # it leaves ringing that the search for an unmodelled pole then mistakes for a mode.
        guess_w = float(np.clip(band.guess.omega_d_rad_s, w_lo, w_hi))
        grid = np.union1d(grid[grid <= w_hi], [guess_w])
        for a, b in band.exclude:
            grid = grid[(grid < a) | (grid > b)]
        if grid.size == 0:
            continue
        sig0 = max(float(band.guess.sigma_per_s), 1e-4)
        sigmas = np.array(sorted({float(np.clip(s, band.sigma_min_per_s, band.sigma_max_per_s))
                                  for s in (min(sig0, 4.0 / T), 0.2 / T, 1.0 / T)}))
        best = _scan(t, v, omega_rad_s, t_ref, fixed + tuple(kept), t_start, grid, sigmas)
        n_par = _n_steady(omega_rad_s) + 2 * len(fixed) + 4 * (len(kept) + 1)
        s2 = best[0] / max(1, t.size - n_par)
        if rss - best[0] > significance * s2:
            kept.append(best[1])
            kept_bands.append((*_allowed_segment(best[1].omega_d_rad_s, w_lo, w_hi, band.exclude),
                               band.sigma_min_per_s, band.sigma_max_per_s))
            kept_idx.append(band_index)
            kept_priors.append(None)
            rss = best[0]
    prior_info = None
    if kept:
        noise_scale = math.sqrt(rss / max(1, t.size - _n_steady(omega_rad_s) - 2 * len(fixed) - 4 * len(kept)))
        kept = list(_refine(t, v, omega_rad_s, t_ref, tuple(kept), t_start, kept_bands, fixed, kept_priors, noise_scale))
        if any(pr is not None for pr in kept_priors):
            prior_info = np.zeros((2 * len(kept), 2 * len(kept)))
            for k, pr in enumerate(kept_priors):
                if pr is not None:
                    prior_info[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = pr[1]
    mask = (False,) * len(fixed) + (True,) * len(kept)
    fit = fit_sine(t, v, omega_rad_s, fixed + tuple(kept), t_ref_s=t_ref, refined_poles=mask,
                   pole_prior_covariance=fixed_covariance, refined_prior_information=prior_info)
    return dataclasses.replace(fit, pole_sources=tuple(kept_idx))


def _allowed_segment(omega_rad_s: float, w_lo: float, w_hi: float, exclude) -> tuple[float, float]:
    """The part of ``[w_lo, w_hi]`` between the band's exclusions that holds ``omega_rad_s`` (a
    scanned pole, never inside one): where its refinement may move it. The exclusions are the
    scan's: another mode's band, or a line's own frequency, where a pole cannot be told from the
    steady state. Refined into one, an unmodelled pole became undamped at a line's frequency
    (0.9000 rad/s against the line at 0.9, decay 1e-6 /s) and took most of the line with it,
    leaving a point three times its truth under a bound a thirtieth of the error."""
    for a, b in exclude:
        if b < omega_rad_s:
            w_lo = max(w_lo, b)
        elif a > omega_rad_s:
            w_hi = min(w_hi, a)
    return w_lo, w_hi


def _real_matrix(c: complex) -> np.ndarray:
    """Real 2x2 matrix of multiplication by ``c`` acting on ``(Re z, Im z)``."""
    return np.array([[c.real, -c.imag], [c.imag, c.real]])


def phasor_ratio(response: SineFit, force: SineFit) -> tuple[complex, np.ndarray]:
    """``H = Y_r / Y_f`` and the 2x2 covariance of ``(Re H, Im H)`` (first-order propagation).

    ``dH = dY_r / Y_f - H dY_f / Y_f``; the channels' noises are independent.
    """
    if abs(force.phasor) == 0:
        raise DataQualityError("phasor ratio: the force phasor is zero (no excitation measured)")
    h = response.phasor / force.phasor
    m_r = _real_matrix(1.0 / force.phasor)
    m_f = _real_matrix(-h / force.phasor)
    cov = m_r @ response.covariance @ m_r.T + m_f @ force.covariance @ m_f.T
    return complex(h), cov


def confidence_radius(covariance: np.ndarray, confidence: float) -> float:
    """Radius ``r`` with ``P(|error| <= r) >= confidence`` for a 2-D Gaussian error.

    Uses the largest eigenvalue (a circle containing the confidence ellipse):
    ``r = sqrt(lambda_max * chi2_2(confidence))``, ``chi2_2(p) = -2 ln(1 - p)``.
    """
    if not 0 < confidence < 1:
        raise ValueError(f"confidence: expected a probability in (0, 1), found {confidence!r}")
    lam = float(np.max(np.linalg.eigvalsh(0.5 * (covariance + covariance.T))))
    return float(np.sqrt(max(lam, 0.0) * -2.0 * np.log1p(-confidence)))


def cramer_rao_phasor_variance(noise_rms: float, n_samples: int) -> float:
    """Cramer-Rao bound on the variance of each phasor component, ``2 s^2 / N``.

    For a sinusoid of known frequency in white Gaussian noise sampled over whole periods.
    """
    return 2.0 * float(noise_rms) ** 2 / int(n_samples)
