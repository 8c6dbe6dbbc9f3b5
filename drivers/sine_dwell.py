"""Sine-dwell measurement on any rig: the loop's Experiment protocol over real or fake hardware.

One :meth:`SineDwellExperiment.measure` call (a *dwell*):

1. checks the command against the procedure's safety limits (nothing is sent otherwise);
2. plans the acquisition: coherent sampling at ``samples_per_period`` per excitation period
   (capped so a dwell has at most ``max_samples`` samples), a short skip (``skip_periods``,
   at least ``skip_s``) for the fast, unmodelled modes, and a fit window long enough to
   separate the excitation from the nearest modelled mode's ringing
   (``separation_cycles`` beat periods ``2 pi / |omega - omega_k|``) but never longer than
   ``max_window_s``;
3. applies the sine and acquires; the samples are checked (finite, not clipped, uniformly
   spaced timestamps) and a dwell with bad data is discarded and measured again (up to
   ``max_attempts``), never used;
4. fits both channels with :func:`setmem_hil.estimation.sine_fit.fit_sine_with_transients`: the IEEE-1057
   sine fit plus decaying regressors for the modelled modes' transients, with poles from the
   current model (eq. 2.25 midpoint; bands from the interval model) refined on the data, and a
   search for one unmodelled mode near ``omega``. When the model's pole intervals are already
   narrow the poles are *fixed* instead and their interval half-widths enter the bound as a
   worst-case linearised term; with ``learn_poles`` each dwell's posterior pole estimate is the
   next dwell's prior (:class:`PoleTracker`);
5. detects settling: the two halves of the window must give estimates that agree within their
   uncertainty (chi-square test at ``settle_confidence``); otherwise the window is extended
   (up to ``safety.max_dwell_s``);
6. returns ``g(j omega) = Y_response / Y_force`` with the absolute bound
   ``R = radius(confidence) + transient terms + extra_bound(omega)`` (transient terms: the
   fixed poles' worst case and the halves' difference beyond its noise RMS) (eq. 3.7: the identification
   needs ``|g - g_0| <= R``), and stops the exciter, also on every abort path.

Faults: a :class:`setmem_hil.errors.DataQualityError` discards the dwell and re-measures; a
:class:`setmem_hil.errors.DeviceError` (timeout, frame error, disconnect) stops the exciter,
reconnects when the rig can (:class:`~setmem_hil.drivers.protocols.ReconnectableRig`) and
re-runs the dwell. After ``max_attempts`` the last error is raised with a message listing every
attempt. ``KeyboardInterrupt`` stops the exciter and propagates.

Example
-------
>>> from setmem_hil.experiment_factory import dwell_experiment
>>> from setmem_hil.io.procedure import default_procedure
>>> from setmem_hil.loopback.rigs import open_serial_loopback_rig
>>> procedure = default_procedure()
>>> with dwell_experiment(procedure, open_serial_loopback_rig(procedure, seed=1)) as exp:
...     m = exp.measure(3.0)
"""

from __future__ import annotations

import atexit
import dataclasses
import logging
import math
import weakref
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from setmem_hil.drivers.protocols import (
    MeasurementIndexedRig,
    RateConfigurableSensor,
    ReconnectableRig,
    Rig,
    SampleBlock,
    WaitingSensor,
)
from setmem_hil.drivers.safety import SafeExciter, check_dwell, check_sine_command, output_guard, safe_stop
from setmem_hil.errors import DataQualityError, DeviceError, SafetyLimitError
from setmem_hil.model.experiment import Measurement
from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.io.procedure import SafetyLimits
from setmem_hil.estimation.sine_fit import (
    DampedPole,
    PoleSearchBand,
    SineFit,
    confidence_radius,
    fit_sine,
    fit_sine_with_transients,
    phasor_ratio,
)

log = logging.getLogger(__name__)


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


@dataclass(frozen=True)
class DwellPlan:
    """A planned dwell: sample rate, skip and window (seconds)."""

    omega_rad_s: float
    sample_rate_hz: float
    skip_s: float
    window_s: float
    n_samples: int


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


def pole_bands(model: IntervalModel | ModalParameters | None, relative_band: float = 0.15) -> tuple[PoleSearchBand, ...]:
    """Pole estimates and search bands of the modelled modes.

    From an :class:`IntervalModel`: midpoint poles (eq. 2.25) and ``omega_n`` bands
    ``[sqrt(a0_lower), sqrt(a0_upper)]``; damping from the ``a1`` midpoint. From a point model:
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
            out.append(PoleSearchBand(DampedPole.from_modal(wn, a1 / (2 * wn)), w_lo, w_hi))
        return tuple(out)
    out = []
    for wn, z in zip(model.natural_frequencies, model.damping_ratios):
        out.append(PoleSearchBand(DampedPole.from_modal(wn, z), wn * (1 - relative_band), wn * (1 + relative_band)))
    return tuple(out)


class SineDwellExperiment:
    """The :class:`setmem_hil.model.experiment.Experiment` protocol on a :class:`Rig`.

    Parameters
    ----------
    rig : Rig
        Exciter + sensor (+ optional capabilities of ``setmem_hil.drivers.protocols``).
    limits : SafetyLimits
        Enforced before any command is sent.
    settings : DwellSettings, optional
    model : IntervalModel or ModalParameters, optional
        Current model for the transient poles (the prior's bounds at the start); see
        :meth:`update_model`.
    extra_bound : callable, optional
        ``extra_bound(omega) -> float`` added to every bound (e.g. ``|W1(j omega)|`` for
        unmodelled dynamics, section 6.2).

    Attributes
    ----------
    n_measured : int
        Measurements taken so far; the rig's noise of dwell ``n`` is seeded with it (set it when
        resuming a campaign from its journal).
    last_result : DwellResult or None
    counters : dict
        Discarded dwells and device faults survived, per kind.
    pole_tracker : PoleTracker
        Pole estimates carried between dwells (used with ``settings.learn_poles``).

    Notes
    -----
    A campaign that calls :meth:`update_model` with each iteration's interval model (eq.
    5.4-5.5) narrows the pole bands the dwells search; the result still depends only on the
    model and ``(seed, n_measured)``, so resumed campaigns stay reproducible.
    """

    def __init__(
        self,
        rig: Rig,
        limits: SafetyLimits,
        settings: DwellSettings | None = None,
        model: IntervalModel | ModalParameters | None = None,
        extra_bound: Callable[[float], float] | None = None,
    ):
        self.rig = rig
        self.limits = limits
        self.settings = settings or DwellSettings()
        if not 0 < self.settings.amplitude_n <= limits.max_amplitude_n:
            raise SafetyLimitError(
                f"dwell amplitude {self.settings.amplitude_n:g} N outside the safety limit (0, {limits.max_amplitude_n:g}] N"
            )
        self.exciter = SafeExciter(rig.exciter, limits)
        self.extra_bound = extra_bound
        self.model: IntervalModel | ModalParameters | None = model
        self.n_measured = 0
        self.last_result: DwellResult | None = None
        self.counters: dict[str, int] = {}
        self.pole_tracker = PoleTracker()
        self._closed = False
        self._failed_attempts = 0  # attempts spent on measurements that raised (since start)
        # interpreter exit without close(): still command zero output and release the rig
        ref = weakref.ref(self)
        self._atexit = lambda: (lambda e: e is not None and e.close())(ref())
        atexit.register(self._atexit)

    # -- model -----------------------------------------------------------------------------
    def update_model(self, model: IntervalModel | ModalParameters | None) -> None:
        """Use this model's poles for the transients of later dwells."""
        self.model = model

    # -- planning --------------------------------------------------------------------------
    def plan(self, omega_rad_s: float) -> DwellPlan:
        """Sample rate, skip and window for a dwell at ``omega_rad_s`` (see the module docs)."""
        s = self.settings
        w = float(omega_rad_s)
        period = 2 * math.pi / w
        window = max(s.min_periods * period, s.min_window_s)
        for band in pole_bands(self.model):
            gap = max(band.omega_min_rad_s - w, w - band.omega_max_rad_s, abs(w - band.guess.omega_d_rad_s) * 0.5, 0.0)
            gap = max(gap, 1e-9)
            window = max(window, s.separation_cycles * 2 * math.pi / gap)
        window = min(window, max(s.max_window_s, s.min_periods * period, s.min_window_s))
        rate = s.samples_per_period / period
        if rate * window > s.max_samples:
            rate = max(s.max_samples / window, s.min_samples_per_period / period)
        n = int(math.ceil(window * rate))
        if n > s.max_samples:
            n = s.max_samples
            window = n / rate
        skip = max(s.skip_periods * period, s.skip_s)
        return DwellPlan(w, rate, skip, n / rate, n)

    # -- measurement -----------------------------------------------------------------------
    def measure(self, omega_rad_s: float) -> Measurement:
        """One dwell at ``omega_rad_s`` (Experiment protocol); the exciter is at zero after it."""
        if self._closed:
            raise DeviceError("sine dwell: measure() after close()")
        w = float(omega_rad_s)
        check_sine_command(self.limits, w, self.settings.amplitude_n)
        plan = self.plan(w)
        check_dwell(self.limits, plan.skip_s + plan.window_s)
        errors: list[str] = []
        last_exc: BaseException | None = None
        for attempt in range(self.settings.max_attempts):
            try:
                result = self._dwell(plan, attempt)
            except DataQualityError as exc:
                safe_stop(self.exciter)
                self._count("discarded_dwell")
                errors.append(f"attempt {attempt + 1}: data discarded: {exc}")
                last_exc = exc
                continue
            except DeviceError as exc:
                safe_stop(self.exciter)
                self._count("device_error")
                errors.append(f"attempt {attempt + 1}: device fault: {exc}")
                last_exc = exc
                self._try_reconnect(errors)
                continue
            except BaseException:
                safe_stop(self.exciter)
                raise
            self.n_measured += 1
            self.last_result = result
            if self.settings.learn_poles:
                self._learn(result.response_fit)
            return result.measurement
        self._failed_attempts += self.settings.max_attempts
        summary = "; ".join(errors)
        msg = f"sine dwell at {w:g} rad/s failed after {self.settings.max_attempts} attempts ({summary})"
        if isinstance(last_exc, DeviceError):
            raise DeviceError(msg) from last_exc
        raise DataQualityError(msg) from last_exc

    def _learn(self, fit: SineFit) -> None:
        """Store this dwell's posterior poles of modelled modes in the tracker."""
        if fit.pole_covariance is None:
            return
        refined = fit.poles[len(fit.poles) - len(fit.pole_sources) :]
        for k, (index, pole) in enumerate(zip(fit.pole_sources, refined)):
            if index >= 0:
                self.pole_tracker.update(index, pole, fit.pole_covariance[2 * k : 2 * k + 2, 2 * k : 2 * k + 2])

    def _count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    def _try_reconnect(self, errors: list[str], tries: int = 3) -> None:
        if not isinstance(self.rig, ReconnectableRig):
            return
        for k in range(tries):
            try:
                self.rig.reconnect()
                self._count("reconnect")
                return
            except DeviceError as exc:
                errors.append(f"reconnect {k + 1} failed: {exc}")
                self._count("reconnect_failed")

    def _dwell(self, plan: DwellPlan, attempt: int) -> DwellResult:
        rig, sensor = self.rig, self.rig.sensor
        if isinstance(rig, MeasurementIndexedRig):
            # attempts of earlier measurements that failed for good get their own streams
            rig.begin_measurement(self.n_measured, self._failed_attempts + attempt)
        if isinstance(sensor, RateConfigurableSensor):
            sensor.set_sample_rate(plan.sample_rate_hz)
        elif abs(rig.metadata.sample_rate_hz - plan.sample_rate_hz) > 1e-9 * plan.sample_rate_hz:
            plan = self._replan_fixed_rate(plan, rig.metadata.sample_rate_hz)
        # output_guard: zero output however the block ends; a failing stop during an abort is
        # logged and never replaces the original exception (so Ctrl-C stays Ctrl-C)
        with output_guard(self.exciter):
            self.exciter.set_sine(plan.omega_rad_s, self.settings.amplitude_n)
            if isinstance(sensor, WaitingSensor):
                sensor.wait(plan.skip_s)
            else:
                sensor.acquire(plan.skip_s)
            block = sensor.acquire(plan.window_s)
            check_block(block, rig.metadata.force_range_n, rig.metadata.response_range, plan.sample_rate_hz)
            dwell_s = plan.skip_s + plan.window_s
            extensions = 0
            while True:
                result = self._estimate(plan, block, attempt, dwell_s, extensions)
                if result is not None:
                    return result
                if extensions >= self.settings.max_extensions or dwell_s + plan.window_s > self.limits.max_dwell_s:
                    raise DataQualityError(
                        f"response at {plan.omega_rad_s:g} rad/s not settled after {dwell_s:.1f} s "
                        "(the halves of the window disagree beyond their uncertainty)"
                    )
                # consecutive windows: the next estimate uses the newest window only
                block = sensor.acquire(plan.window_s)
                check_block(block, rig.metadata.force_range_n, rig.metadata.response_range, plan.sample_rate_hz)
                dwell_s += plan.window_s
                extensions += 1

    def _replan_fixed_rate(self, plan: DwellPlan, rate_hz: float) -> DwellPlan:
        n = int(math.ceil(plan.window_s * rate_hz))
        return DwellPlan(plan.omega_rad_s, rate_hz, plan.skip_s, n / rate_hz, n)

    def _fit_response(self, t, y, w, t_ref, window_s) -> tuple[SineFit, float]:
        """Response fit with transients; returns the fit and the worst-case fixed-pole term.

        Per modelled mode: with ``learn_poles`` and an estimate from earlier dwells, the pole is
        refined with that estimate as a Gaussian prior; else a pole whose model interval is
        narrow enough is fixed with a worst-case term; else it is searched in its band and
        refined on the data. An unmodelled mode near the excitation is searched too.
        """
        bands = pole_bands(self.model)
        # an unmodelled mode near the excitation rings too: search outside the modelled bands
        # and outside +-pi/T of omega (a pole there cannot be told from the steady state)
        resolve = math.pi / max(window_s, 1e-9)
        exclude = tuple((b.omega_min_rad_s - resolve, b.omega_max_rad_s + resolve) for b in bands) + ((w - resolve, w + resolve),)
        generic = PoleSearchBand(DampedPole(0.01 * w, w), w / self.settings.unmodelled_band, w * self.settings.unmodelled_band, exclude)
        limit = self.settings.fixed_pole_phase_limit
        fixed: list[DampedPole] = []
        fixed_cov: list[np.ndarray] = []
        halfwidths: list[tuple[float, float]] = []
        search: list[PoleSearchBand] = []
        search_index: list[int] = []
        priors: dict[int, tuple[DampedPole, np.ndarray]] = {}
        for i, b in enumerate(bands):
            learned = self.pole_tracker.estimate(i) if self.settings.learn_poles else None
            if learned is not None:
                priors[len(search)] = learned  # refine with the earlier dwells as a prior
                search.append(b)
                search_index.append(i)
                continue
            half_w = 0.5 * (b.omega_max_rad_s - b.omega_min_rad_s)
            if isinstance(self.model, IntervalModel):
                half_s = 0.25 * (self.model.upper[i, 0] - self.model.lower[i, 0])
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
        term = 0.0
        if any(h != (0.0, 0.0) for h in halfwidths):
            term = _fixed_pole_term(t, y, w, t_ref, fit.poles, halfwidths)
        return fit, term

    def _estimate(self, plan, block, attempt, dwell_s, extensions) -> DwellResult | None:
        t, f, y = block.t_s, block.force, block.response
        w = plan.omega_rad_s
        t_ref = float(t[0])
        window_s = float(t[-1] - t[0])
        rfit, transient_term = self._fit_response(t, y, w, t_ref, window_s)
        ffit = fit_sine(t, f, w, t_ref_s=t_ref)
        h, cov = phasor_ratio(rfit, ffit)
        # settling: the halves must agree within their uncertainty
        half = t.size // 2
        mismatch = 0.0
        if half >= 16 and rfit.n_params < half - 4:
            ra = fit_sine(t[:half], y[:half], w, rfit.poles, t_ref_s=t_ref)
            rb = fit_sine(t[half:], y[half:], w, rfit.poles, t_ref_s=t_ref)
            fa = fit_sine(t[:half], f[:half], w, t_ref_s=t_ref)
            fb = fit_sine(t[half:], f[half:], w, t_ref_s=t_ref)
            ha, ca = phasor_ratio(ra, fa)
            hb, cb = phasor_ratio(rb, fb)
            d = np.array([(ha - hb).real, (ha - hb).imag])
            cd = ca + cb
            try:
                stat = float(d @ np.linalg.solve(cd, d))
            except np.linalg.LinAlgError:
                stat = math.inf
            if stat > -2.0 * math.log1p(-self.settings.settle_confidence):
                return None
            # transient-mismatch term: what remains of an unmodelled or mis-modelled transient
            # shows as a difference between the halves (the later half has less of it) beyond
            # the difference their noise explains (its RMS, sqrt(trace(cov_a + cov_b)))
            excess = max(0.0, abs(ha - hb) - math.sqrt(float(np.trace(cd))))
            mismatch = self.settings.mismatch_factor * excess
        radius = confidence_radius(cov, self.settings.confidence)
        t_term = transient_term / abs(ffit.phasor)
        extra = float(self.extra_bound(w)) if self.extra_bound is not None else 0.0
        t_term += mismatch
        bound = radius + t_term + extra
        if not (math.isfinite(bound) and math.isfinite(h.real) and math.isfinite(h.imag)):
            raise DataQualityError(f"dwell at {w:g} rad/s: non-finite estimate")
        m = Measurement(w, complex(h), float(bound))
        return DwellResult(m, plan, rfit, ffit, cov, radius, t_term, extra, dwell_s, attempt + 1, extensions)

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> None:
        """Zero output and release the rig (idempotent)."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self._atexit)
        try:
            safe_stop(self.exciter)
        finally:
            self.rig.close()

    def __enter__(self) -> "SineDwellExperiment":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _fixed_pole_term(t, y, w, t_ref, poles, halfwidths) -> float:
    """Worst-case linearised phasor error from fixed poles known to within half-widths.

    ``dY = G dtheta`` with ``G`` the first two rows of ``-X^+ J_pole`` (the change of the
    linear coefficients when the pole parameters move); ``|dY| <= sum_i |G_i| h_i``.
    """
    from setmem_hil.estimation.sine_fit import _design, _pole_jacobian_columns, _solve

    t0 = float(t[0])
    X = _design(t, w, t_ref, poles, t0)
    coef, _ = _solve(X, y)
    cols = _pole_jacobian_columns(t, poles[: len(halfwidths)], coef, t0)
    if not cols:
        return 0.0
    Jp = np.column_stack(cols)
    G = -np.linalg.lstsq(X, Jp, rcond=None)[0][:2]
    h = np.array([q for hw, hs in halfwidths for q in (hs, hw)])
    return float(np.sum(np.hypot(G[0], G[1]) * h))


def check_block(block: SampleBlock, force_range_n: float, response_range: float, rate_hz: float) -> None:
    """Raise DataQualityError for unusable samples: non-finite, clipped, or irregular timestamps."""
    t, f, y = (np.asarray(a, dtype=float) for a in (block.t_s, block.force, block.response))
    if not (t.size == f.size == y.size) or t.size < 8:
        raise DataQualityError(f"sample block: channel lengths {t.size}, {f.size}, {y.size} (need equal, >= 8)")
    bad = int(np.sum(~np.isfinite(t)) + np.sum(~np.isfinite(f)) + np.sum(~np.isfinite(y)))
    if bad:
        raise DataQualityError(f"sample block: {bad} NaN or infinite samples")
    clipped = int(np.sum(np.abs(f) >= 0.999 * force_range_n) + np.sum(np.abs(y) >= 0.999 * response_range))
    if clipped:
        raise DataQualityError(f"sample block: {clipped} samples at full scale (sensor saturation)")
    dt = np.diff(t)
    expected = 1.0 / rate_hz
    if np.any(np.abs(dt - expected) > 1e-6 * expected + 1e-9):
        k = int(np.argmax(np.abs(dt - expected)))
        raise DataQualityError(f"sample block: timestamp jump of {dt[k]:.6g} s at sample {k + 1} (expected {expected:.6g} s)")


def _concat(a: SampleBlock, b: SampleBlock) -> SampleBlock:
    dt = float(a.t_s[1] - a.t_s[0])
    if abs(float(b.t_s[0] - a.t_s[-1]) - dt) > 1e-6 * dt + 1e-9:
        raise DataQualityError("sample blocks: the extension is not contiguous with the first window")
    return SampleBlock(np.concatenate([a.t_s, b.t_s]), np.concatenate([a.force, b.force]), np.concatenate([a.response, b.response]))
