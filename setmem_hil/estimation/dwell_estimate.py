"""Numerics of one sine dwell: planning, pole bands, the transient-aware estimate and its bound.

Pure functions and data (no device I/O): :func:`plan_dwell` (sample rate, skip and window from
the current pole intervals), :func:`pole_bands` (eq. 2.25 midpoint poles and their
``omega_n`` bands), :class:`PoleTracker` (pole posteriors carried between dwells),
:func:`fit_response` and :func:`estimate_dwell` (the response and force phasors with modelled
transients, their ratio ``g`` and the bound ``R`` covering noise, transient mismatch and the
extra unmodelled-dynamics term, eq. 3.7), :func:`check_block` (refuse unusable samples), and
the same for a multisine record (:func:`plan_multisine`, :func:`estimate_multisine`: one joint
fit of all lines and the transients, a bound per line). The
device side, :class:`setmem_hil.drivers.sine_dwell.SineDwellExperiment`, drives the rig and
calls these.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.sine_fit import (
    DampedPole,
    PoleSearchBand,
    SineFit,
    confidence_radius,
    fit_sine,
    fit_sine_with_transients,
    phasor_ratio,
)
from setmem_hil.model.experiment import Measurement
from setmem_hil.model.modal_model import IntervalModel, ModalParameters

__all__ = ["DwellSettings", "DwellPlan", "DwellResult", "PoleTracker", "pole_bands", "plan_dwell", "replan_fixed_rate",
           "fit_response", "estimate_dwell", "fixed_pole_terms", "check_block", "MultisinePlan", "plan_multisine",
           "record_duration_s", "estimate_multisine"]


@dataclass(frozen=True)
class DwellSettings:
    """How a dwell is planned, checked and bounded (defaults suit the thesis beam).

    Attributes
    ----------
    amplitude_n : float
        Force amplitude (checked against ``SafetyLimits.max_amplitude_n``).
    samples_per_period : int
        Coherent sampling rate, samples per excitation period.
    max_samples : int
        Most samples in one acquisition (the sample rate is lowered to respect it, never below
        ``min_samples_per_period``).
    min_samples_per_period : int
    min_periods : int
        Shortest fit window, in excitation periods.
    min_window_s : float
        Shortest fit window in seconds (lets unmodelled fast modes ring down and be resolved).
    separation_cycles : float
        Fit window of at least this many beat periods ``2 pi / |omega - omega_k|`` with the
        nearest modelled mode (so its ringing is separable from the steady state).
    max_window_s : float
        Longest first window.
    skip_periods, skip_s : float
        Samples discarded after the sine starts: ``max(skip_periods periods, skip_s)``.
    confidence : float
        Confidence of the returned bound (radius of the fitted covariance, chi-square with 2
        degrees of freedom: 0.9995 is 3.9 sigma).
    settle_confidence : float
        Level of the halves-agree settling test.
    max_extensions : int
        Times the window may be extended when the halves disagree.
    max_attempts : int
        Dwells tried per measurement (discarded data, device faults) before giving up.
    multisine_max_samples : int
        Most samples in one multisine acquisition (its lines share one record, so it may be
        longer than ``max_samples``).
    learn_poles : bool
        Carry the modelled modes' pole estimates from dwell to dwell (:class:`PoleTracker`,
        each dwell's posterior is the next one's prior): near a mode this brings the variance
        close to the Cramer-Rao bound at short dwells. Off by default because a
        measurement then depends on the earlier dwells' raw data, so a campaign resumed from
        its journal would no longer repeat an uninterrupted run bit for bit.
    mismatch_factor : float
        The bound includes ``mismatch_factor`` times the excess of ``|g_first_half -
        g_second_half|`` over its noise RMS (transient mismatch: unmodelled modes and pole
        errors that the fitted covariance misses).
    unmodelled_band : float
        A further transient pole (an unmodelled mode) is searched in ``omega / b .. omega b``.
    fixed_pole_phase_limit : float
        Use the model's poles without refinement when their interval half-width times the
        window length is below this (radians of phase drift).
    """

    amplitude_n: float = 1.0
    samples_per_period: int = 32
    max_samples: int = 2048
    min_samples_per_period: int = 6
    min_periods: int = 12
    min_window_s: float = 10.0
    separation_cycles: float = 2.0
    max_window_s: float = 120.0
    skip_periods: float = 0.5
    skip_s: float = 2.0
    confidence: float = 0.9995
    settle_confidence: float = 0.999
    max_extensions: int = 2
    max_attempts: int = 5
    fixed_pole_phase_limit: float = 0.05
    unmodelled_band: float = 1.5
    mismatch_factor: float = 1.0
    learn_poles: bool = False
    multisine_max_samples: int = 16384


@dataclass(frozen=True)
class DwellPlan:
    """A planned dwell: sample rate, skip and window (seconds)."""

    omega_rad_s: float
    sample_rate_hz: float
    skip_s: float
    window_s: float
    n_samples: int

    @property
    def omegas_rad_s(self) -> tuple[float, ...]:
        """The excited frequencies (one; a :class:`MultisinePlan` has several)."""
        return (self.omega_rad_s,)


@dataclass(frozen=True)
class DwellResult:
    """Everything one dwell produced (kept as ``last_result`` for diagnostics and benchmarks)."""

    measurement: Measurement
    plan: DwellPlan
    response_fit: SineFit
    force_fit: SineFit
    covariance: np.ndarray
    radius: float
    transient_term: float
    extra_term: float
    dwell_s: float
    attempts: int
    extensions: int


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    n = 2 * len(blocks)
    out = np.zeros((n, n))
    for k, b in enumerate(blocks):
        out[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = b
    return out


class PoleTracker:
    """Sequential Bayesian estimate of the modelled modes' poles over dwells.

    Each dwell refines a mode's pole ``(sigma, omega_d)`` with the tracker's current estimate
    as a Gaussian prior (:func:`setmem_hil.estimation.sine_fit.fit_sine_with_transients`, ``pole_priors``);
    the posterior (mean and covariance: data and prior information combined) replaces the
    tracker's estimate. The pole uncertainty, which dominates the variance of a short dwell near
    a mode, thus shrinks with every dwell and stays in each dwell's covariance.
    """

    def __init__(self):
        self._est: dict[int, tuple[DampedPole, np.ndarray]] = {}
        self.updates = 0

    def estimate(self, index: int) -> tuple[DampedPole, np.ndarray] | None:
        return self._est.get(index)

    def update(self, index: int, pole: DampedPole, cov: np.ndarray) -> bool:
        cov = np.asarray(cov, dtype=float)
        cov = 0.5 * (cov + cov.T)
        if cov.shape != (2, 2) or not np.all(np.isfinite(cov)) or np.linalg.det(cov) <= 0 or cov[0, 0] <= 0:
            return False
        self._est[index] = (pole, cov)
        self.updates += 1
        return True

    def state(self) -> tuple:
        """Every estimate as ``(index, sigma, omega_d, cov)``, by index (``update`` restores them)."""
        return tuple((index, pole.sigma_per_s, pole.omega_d_rad_s, np.asarray(cov).tolist()) for index, (pole, cov) in sorted(self._est.items()))


def pole_bands(model: IntervalModel | ModalParameters | None, relative_band: float = 0.15) -> tuple[PoleSearchBand, ...]:
    """Pole estimates and search bands of the modelled modes.

    From an :class:`IntervalModel`: midpoint poles (eq. 2.25) and ``omega_n`` bands
    ``[sqrt(a0_lower), sqrt(a0_upper)]``; damping from the ``a1`` midpoint, the decay rate kept
    within ``a1 / 2`` of the interval. From a point model:
    ``omega_n (1 +- relative_band)``.
    """
    if model is None:
        return ()
    if isinstance(model, IntervalModel):
        lo, hi = model.lower, model.upper
        out = []
        for i in range(model.n_modes):
            w_lo, w_hi = math.sqrt(max(lo[i, 1], 0.0)), math.sqrt(max(hi[i, 1], 0.0))
            wn = 0.5 * (w_lo + w_hi)
            a1 = 0.5 * (lo[i, 0] + hi[i, 0])
            if wn <= 0:
                continue
            # the identified a1 interval holds the true decay rate a1 / 2 (guaranteed bounds)
            out.append(PoleSearchBand(DampedPole.from_modal(wn, a1 / (2 * wn)), w_lo, w_hi,
                                      sigma_min_per_s=max(1e-6, 0.5 * lo[i, 0]), sigma_max_per_s=max(0.5 * hi[i, 0], 1e-6)))
        return tuple(out)
    out = []
    for wn, z in zip(model.natural_frequencies, model.damping_ratios):
        out.append(PoleSearchBand(DampedPole.from_modal(wn, z), wn * (1 - relative_band), wn * (1 + relative_band)))
    return tuple(out)


def plan_dwell(settings: DwellSettings, model, omega_rad_s: float) -> DwellPlan:
    """Sample rate, skip and window for a dwell at ``omega_rad_s``: long enough to separate the
    excitation from the modelled modes' transients (``separation_cycles`` over the gap to each
    pole band), capped by ``max_window_s`` and ``max_samples``."""
    s = settings
    w = float(omega_rad_s)
    period = 2 * math.pi / w
    window = max(s.min_periods * period, s.min_window_s)
    for band in pole_bands(model):
        gap = max(band.omega_min_rad_s - w, w - band.omega_max_rad_s, abs(w - band.guess.omega_d_rad_s) * 0.5, 0.0)
        gap = max(gap, 1e-9)
        window = max(window, s.separation_cycles * 2 * math.pi / gap)
    window = min(window, max(s.max_window_s, s.min_periods * period, s.min_window_s))
    rate, n = _sampling(s, window, period, s.max_samples)
    skip = max(s.skip_periods * period, s.skip_s)
    return DwellPlan(w, rate, skip, n / rate, n)


def _sampling(s: DwellSettings, window: float, period: float, max_samples: int) -> tuple[float, int]:
    """Sample rate and count for a window: ``samples_per_period`` of ``period`` (the shortest
    excited period), lowered to fit ``max_samples`` but never below ``min_samples_per_period``,
    then the count capped (the window shortens)."""
    rate = s.samples_per_period / period
    if rate * window > max_samples:
        rate = max(max_samples / window, s.min_samples_per_period / period)
    return rate, min(int(math.ceil(window * rate)), max_samples)



def replan_fixed_rate(plan: DwellPlan | MultisinePlan, rate_hz: float) -> DwellPlan | MultisinePlan:
    """The same dwell or multisine record at a rate the sensor cannot change."""
    n = int(math.ceil(plan.window_s * rate_hz))
    return dataclasses.replace(plan, sample_rate_hz=rate_hz, window_s=n / rate_hz, n_samples=n)



def fit_response(settings: DwellSettings, model, tracker: PoleTracker, t, y, w, t_ref, window_s) -> tuple[SineFit, np.ndarray]:
    """Response fit with transients; returns the fit and the worst-case fixed-pole term of each
    line of ``w`` (:func:`fixed_pole_terms`).

    Per modelled mode: with ``learn_poles`` and an estimate from earlier dwells, the pole is
    refined with that estimate as a Gaussian prior; else a pole whose model interval is
    narrow enough is fixed with a worst-case term; else it is searched in its band and
    refined on the data. An unmodelled mode near the excitation is searched too.
    """
    bands = pole_bands(model)
    # an unmodelled mode near the excitation rings too: search outside the modelled bands
    # and outside +-pi/T of omega (a pole there cannot be told from the steady state)
    resolve = math.pi / max(window_s, 1e-9)
    lines = np.atleast_1d(np.asarray(w, dtype=float))
    exclude = tuple((b.omega_min_rad_s - resolve, b.omega_max_rad_s + resolve) for b in bands) + tuple(
        (wk - resolve, wk + resolve) for wk in lines)
    centre = float(lines[0]) if lines.size == 1 else float(np.exp(np.mean(np.log(lines))))
    generic = PoleSearchBand(DampedPole(0.01 * centre, centre), float(lines.min()) / settings.unmodelled_band,
                             float(lines.max()) * settings.unmodelled_band, exclude)
    limit = settings.fixed_pole_phase_limit
    fixed: list[DampedPole] = []
    fixed_cov: list[np.ndarray] = []
    halfwidths: list[tuple[float, float]] = []
    search: list[PoleSearchBand] = []
    search_index: list[int] = []
    priors: dict[int, tuple[DampedPole, np.ndarray]] = {}
    for i, b in enumerate(bands):
        learned = tracker.estimate(i) if settings.learn_poles else None
        if learned is not None:
            priors[len(search)] = learned  # refine with the earlier dwells as a prior
            search.append(b)
            search_index.append(i)
            continue
        half_w = 0.5 * (b.omega_max_rad_s - b.omega_min_rad_s)
        if isinstance(model, IntervalModel):
            half_s = 0.25 * (model.upper[i, 0] - model.lower[i, 0])
        else:
            half_s = math.inf
        if max(half_w, half_s) * window_s < limit:
            fixed.append(b.guess)
            fixed_cov.append(np.zeros((2, 2)))
            halfwidths.append((half_w, half_s))
        else:
            search.append(b)
            search_index.append(i)
    search.append(generic)
    search_index.append(-1)
    cov = _block_diag(fixed_cov) if fixed else None
    fit = fit_sine_with_transients(t, y, w, tuple(search), t_ref_s=t_ref, fixed_poles=tuple(fixed),
                                   fixed_covariance=cov, pole_priors=priors)
    fit = dataclasses.replace(fit, pole_sources=tuple(search_index[k] for k in fit.pole_sources))
    terms = np.zeros(lines.size)
    if any(h != (0.0, 0.0) for h in halfwidths):
        terms = fixed_pole_terms(t, y, w, t_ref, fit.poles, halfwidths)
    return fit, terms



def estimate_dwell(settings: DwellSettings, model, tracker: PoleTracker, extra_bound, plan: DwellPlan, block,
                   attempt: int, dwell_s: float, extensions: int) -> DwellResult | None:
    """The frequency-response point of one settled window with its guaranteed-coverage bound, or
    None when the window's halves disagree (not settled yet: extend the dwell)."""
    results = _estimate_lines(settings, model, tracker, extra_bound, plan, plan.omegas_rad_s, block, attempt, dwell_s, extensions)
    return None if results is None else results[0]


def fixed_pole_terms(t, y, w, t_ref, poles, halfwidths) -> np.ndarray:
    """Worst-case linearised phasor error of each line of ``w`` from fixed poles known to within
    half-widths.

    ``dY = G dtheta`` with ``G`` the line's two rows of ``-X^+ J_pole`` (the change of the
    linear coefficients when the pole parameters move); ``|dY| <= sum_i |G_i| h_i``.
    """
    from setmem_hil.estimation.sine_fit import _design, _n_steady, _pole_jacobian_columns, _solve

    n_lines = np.atleast_1d(w).size
    t0 = float(t[0])
    X = _design(t, w, t_ref, poles, t0)
    coef, _ = _solve(X, y)
    cols = _pole_jacobian_columns(t, poles[: len(halfwidths)], coef, t0, _n_steady(w))
    if not cols:
        return np.zeros(n_lines)
    Jp = np.column_stack(cols)
    G = -np.linalg.lstsq(X, Jp, rcond=None)[0]
    h = np.array([q for hw, hs in halfwidths for q in (hs, hw)])
    return np.array([float(np.sum(np.hypot(G[2 * k], G[2 * k + 1]) * h)) for k in range(n_lines)])


def check_block(block, force_range_n: float, response_range: float, rate_hz: float) -> None:
    """Raise DataQualityError for unusable samples: non-finite, clipped, or irregular timestamps.

    ``block`` has ``t_s``, ``force`` and ``response`` arrays (:class:`setmem_hil.drivers.protocols.SampleBlock`).
    """
    t, f, y = (np.asarray(a, dtype=float) for a in (block.t_s, block.force, block.response))
    others = [np.asarray(o, dtype=float) for o in getattr(block, "others", ())]
    sizes = [t.size, f.size, y.size, *(o.size for o in others)]
    if len(set(sizes)) != 1 or t.size < 8:
        raise DataQualityError(f"sample block: channel lengths {', '.join(map(str, sizes))} (need equal, >= 8)")
    bad = int(sum(np.sum(~np.isfinite(a)) for a in (t, f, y, *others)))
    if bad:
        raise DataQualityError(f"sample block: {bad} NaN or infinite samples")
    clipped = int(np.sum(np.abs(f) >= 0.999 * force_range_n) + sum(np.sum(np.abs(a) >= 0.999 * response_range) for a in (y, *others)))
    if clipped:
        raise DataQualityError(f"sample block: {clipped} samples at full scale (sensor saturation)")
    dt = np.diff(t)
    expected = 1.0 / rate_hz
    if np.any(np.abs(dt - expected) > 1e-6 * expected + 1e-9):
        k = int(np.argmax(np.abs(dt - expected)))
        raise DataQualityError(f"sample block: timestamp jump of {dt[k]:.6g} s at sample {k + 1} (expected {expected:.6g} s)")



@dataclass(frozen=True)
class MultisinePlan:
    """A planned multisine record: its lines, sample rate, skip and window (seconds)."""

    omegas_rad_s: tuple[float, ...]
    sample_rate_hz: float
    skip_s: float
    window_s: float
    n_samples: int


def plan_multisine(settings: DwellSettings, model, omegas_rad_s) -> MultisinePlan:
    """One record for several lines: the longest of the lines' own windows (:func:`plan_dwell`)
    and ``separation_cycles`` beat periods of the closest pair of lines, capped like a single
    dwell's window; sampled for the highest line (up to ``multisine_max_samples``); the skip of
    the lowest line."""
    s = settings
    lines = tuple(float(w) for w in omegas_rad_s)
    if len(lines) < 1 or len(set(lines)) != len(lines):
        raise ValueError(f"multisine plan: expected distinct frequencies, found {list(lines)}")
    plans = [plan_dwell(s, model, w) for w in lines]
    window = max(p.window_s for p in plans)
    ordered = sorted(lines)
    if len(ordered) > 1:
        gap = min(b - a for a, b in zip(ordered, ordered[1:]))
        window = max(window, s.separation_cycles * 2 * math.pi / gap)
    longest = 2 * math.pi / ordered[0]
    window = min(window, max(s.max_window_s, s.min_periods * longest, s.min_window_s))
    rate, n = _sampling(s, window, 2 * math.pi / ordered[-1], s.multisine_max_samples)
    skip = max(s.skip_periods * longest, s.skip_s)
    return MultisinePlan(lines, rate, skip, n / rate, n)


def record_duration_s(settings: DwellSettings, plan: MultisinePlan) -> float:
    """The longest a record may play: its skip, window and every allowed extension (its
    multisine's peak guarantee must hold that long)."""
    return plan.skip_s + plan.window_s * (1 + settings.max_extensions)


def estimate_multisine(settings: DwellSettings, model, tracker: PoleTracker, extra_bound, plan: MultisinePlan, block,
                       attempt: int, dwell_s: float, extensions: int) -> list[DwellResult] | None:
    """Every line's frequency-response point of one settled multisine window, each with its own
    guaranteed-coverage bound, or None when the window's halves disagree at some line.

    One joint fit per channel (all lines, the offset and the transients:
    :func:`fit_response`); each line's covariance uses the noise level near that line. The
    settling test and the transient-mismatch term are the single dwell's, per line; the
    settling level is split over the lines (Bonferroni), so a record is not extended more
    often than a single dwell.
    """
    return _estimate_lines(settings, model, tracker, extra_bound, plan, plan.omegas_rad_s, block, attempt, dwell_s, extensions)


def _estimate_lines(settings: DwellSettings, model, tracker: PoleTracker, extra_bound, plan, omegas, block,
                    attempt: int, dwell_s: float, extensions: int) -> list[DwellResult] | None:
    """One settled window's points at ``omegas`` (one sine or a multisine's lines), or None.

    Settling: the two halves of the window must give estimates that agree within their
    uncertainty (chi-square, at ``settle_confidence`` split over the lines). Transient
    mismatch: what remains of an unmodelled or mis-modelled transient shows as a difference
    between the halves (the later half has less of it) beyond the difference their noise
    explains (its RMS, ``sqrt(trace(cov_a + cov_b))``); it is added to the bound.
    """
    t, f = block.t_s, block.force
    lines = np.asarray(omegas, dtype=float)
    n_lines = lines.size
    t_ref = float(t[0])
    window_s = float(t[-1] - t[0])
    ffit = fit_sine(t, f, lines, t_ref_s=t_ref)
    half = t.size // 2
    halves = None
    if half >= 16:
        halves = (fit_sine(t[:half], f[:half], lines, t_ref_s=t_ref), fit_sine(t[half:], f[half:], lines, t_ref_s=t_ref))
    channels = (block.response, *getattr(block, "others", ()))
    # the settling level is split over every line of every channel (Bonferroni)
    threshold = -2.0 * (math.log1p(-settings.settle_confidence) - math.log(n_lines * len(channels)))
    points = []
    for y in channels:
        point = _channel_points(settings, model, tracker, t, y, lines, t_ref, window_s, ffit, halves, threshold)
        if point is None:
            return None
        points.append(point)
    rfit, ratios, transient_terms, mismatch = points[0]
    results = []
    for k, w in enumerate(lines):
        h, cov = ratios[k]
        force_phasor = ffit.line(k).phasor
        radius = confidence_radius(cov, settings.confidence)
        t_term = float(transient_terms[k]) / abs(force_phasor) + float(mismatch[k])
        extra = float(extra_bound(float(w))) if extra_bound is not None else 0.0
        bound = radius + t_term + extra
        if not (math.isfinite(bound) and math.isfinite(h.real) and math.isfinite(h.imag)):
            where = f"dwell at {w:g} rad/s" if n_lines == 1 else f"multisine record, line {w:g} rad/s"
            raise DataQualityError(f"{where}: non-finite estimate")
        others = tuple(_other_point(point, k, force_phasor, settings, extra) for point in points[1:])
        m = Measurement(float(w), complex(h), float(bound), others=others)
        results.append(DwellResult(m, plan, rfit.line(k), ffit.line(k), cov, radius, t_term, extra, dwell_s, attempt + 1, extensions))
    return results


def _channel_points(settings: DwellSettings, model, tracker: PoleTracker, t, y, lines, t_ref, window_s, ffit, halves,
                    threshold):
    """One response channel of a settled window: its transient-aware fit, each line's ratio over
    the force with its covariance, the fixed-pole terms and the halves' mismatch term; None when
    the halves disagree beyond ``threshold`` (not settled)."""
    rfit, transient_terms = fit_response(settings, model, tracker, t, y, lines, t_ref, window_s)
    ratios = [phasor_ratio(rfit.line(k), ffit.line(k)) for k in range(lines.size)]
    mismatch = np.zeros(lines.size)
    half = t.size // 2
    if halves is None or rfit.n_params >= half - 4:
        return rfit, ratios, transient_terms, mismatch
    fa, fb = halves
    ra = fit_sine(t[:half], y[:half], lines, rfit.poles, t_ref_s=t_ref)
    rb = fit_sine(t[half:], y[half:], lines, rfit.poles, t_ref_s=t_ref)
    for k in range(lines.size):
        ha, ca = phasor_ratio(ra.line(k), fa.line(k))
        hb, cb = phasor_ratio(rb.line(k), fb.line(k))
        d = np.array([(ha - hb).real, (ha - hb).imag])
        cd = ca + cb
        try:
            stat = float(d @ np.linalg.solve(cd, d))
        except np.linalg.LinAlgError:
            stat = math.inf
        if stat > threshold:
            return None
        mismatch[k] = settings.mismatch_factor * max(0.0, abs(ha - hb) - math.sqrt(float(np.trace(cd))))
    return rfit, ratios, transient_terms, mismatch


def _other_point(point, k: int, force_phasor: complex, settings: DwellSettings, extra: float) -> tuple[complex, float]:
    """Line ``k`` of another sensor's channel as ``Measurement.others`` carries it: the ratio and
    its bound (confidence radius, transient terms and the same extra term as the control
    output's: ``|W1|`` bounds the unmodelled modes at every sensor, see the simulated beam)."""
    _, ratios, transient_terms, mismatch = point
    h, cov = ratios[k]
    bound = confidence_radius(cov, settings.confidence) + float(transient_terms[k]) / abs(force_phasor) + float(mismatch[k]) + extra
    if not (math.isfinite(bound) and math.isfinite(h.real) and math.isfinite(h.imag)):
        raise DataQualityError("another sensor's channel: non-finite estimate")
    return complex(h), float(bound)
