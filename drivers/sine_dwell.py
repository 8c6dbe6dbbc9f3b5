"""Sine-dwell measurement on any rig: the loop's Experiment protocol over real or fake hardware.

One :meth:`SineDwellExperiment.measure` call (a *dwell*):

1. checks the command against the procedure's safety limits (nothing is sent otherwise);
2. plans the acquisition (numerics in :mod:`setmem_hil.estimation.dwell_estimate`): coherent sampling at ``samples_per_period`` per excitation period
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

:meth:`SineDwellExperiment.measure_multisine` measures several frequencies in one record (a
*multisine dwell*, issue 15): the sum of sinusoids of :func:`setmem_hil.estimation.multisine.design_multisine`
(its peak, not each line, within the amplitude limit), one window planned for all lines
(:func:`~setmem_hil.estimation.dwell_estimate.plan_multisine`), one joint transient-aware fit,
a bound per line; the settling is paid once. The rig's exciter must be a
:class:`~setmem_hil.drivers.protocols.MultisineExciter`.

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
import weakref
from typing import Callable

import numpy as np

from setmem_hil.drivers.protocols import (
    InstrumentTermsSensor,
    MeasurementIndexedRig,
    MultisineExciter,
    RateConfigurableSensor,
    ReconnectableRig,
    RecordedMultisineExciter,
    ResolutionLimitedSensor,
    Rig,
    TermsReportingSensor,
    WaitingSensor,
)
from setmem_hil.drivers.safety import SafeExciter, check_dwell, check_sine_command, output_guard, safe_stop
from setmem_hil.errors import DataQualityError, DeviceError, SafetyLimitError
from setmem_hil.estimation.dwell_record import DwellInputs, corrected_points, dwell_record, results_from_inputs
from setmem_hil.model.experiment import Measurement, RawRecord
from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.io.procedure import SafetyLimits
from setmem_hil.estimation.dwell_estimate import (
    DwellPlan,
    DwellResult,
    DwellSettings,
    MultisinePlan,
    PoleTracker,
    check_block,
    plan_dwell,
    plan_multisine,
    record_duration_s,
    replan_fixed_rate,
)
from setmem_hil.estimation.multisine import design_multisine, line_weights, resolvable_groups
from setmem_hil.estimation.sine_fit import SineFit

log = logging.getLogger(__name__)


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
        self.safe_exciter = SafeExciter(rig.exciter, limits)
        self.extra_bound = extra_bound
        self.model: IntervalModel | ModalParameters | None = model
        self.n_measured = 0
        self.rig_s = 0.0  # device seconds of all dwells so far
        self._device_s = 0.0
        self.last_result: DwellResult | None = None
        self.counters: dict[str, int] = {}
        self.pole_tracker = PoleTracker()
        self._raw: list[RawRecord] = []  # raw records not yet taken (take_raw_records)
        self._inputs: DwellInputs | None = None  # the last settled window's estimator inputs
        self._closed = False
        self._failed_attempts = 0  # attempts spent on measurements that raised (since start)
        # interpreter exit without close(): still command zero output and release the rig
        ref = weakref.ref(self)
        self._atexit = lambda: (lambda e: e is not None and e.close())(ref())
        atexit.register(self._atexit)

    @property
    def exciter(self) -> SafeExciter:
        """The rig's exciter behind the safety checks (what every dwell commands)."""
        return self.safe_exciter

    # -- model -----------------------------------------------------------------------------
    def update_model(self, model: IntervalModel | ModalParameters | None) -> None:
        """Use this model's poles for the transients of later dwells."""
        self.model = model

    # -- planning --------------------------------------------------------------------------
    def plan(self, omega_rad_s: float) -> DwellPlan:
        """Sample rate, skip and window for a dwell at ``omega_rad_s`` (:func:`plan_dwell`)."""
        return plan_dwell(self.settings, self.model, omega_rad_s)

    # -- measurement -----------------------------------------------------------------------
    def measure(self, omega_rad_s: float) -> Measurement:
        """One dwell at ``omega_rad_s`` (Experiment protocol); the exciter is at zero after it."""
        if self._closed:
            raise DeviceError("sine dwell: measure() after close()")
        w = float(omega_rad_s)
        check_sine_command(self.limits, w, self.settings.amplitude_n)
        plan = self.plan(w)
        check_dwell(self.limits, plan.skip_s + plan.window_s)

        def start(plan):
            self.safe_exciter.set_sine(plan.omega_rad_s, self.settings.amplitude_n)

        def estimate(plan, block, attempt, dwell_s, extensions):
            results = self._estimate(plan, block, attempt, dwell_s, extensions)
            return None if results is None else results[0]

        result = self._attempts(f"sine dwell at {w:g} rad/s", plan, start, estimate)
        return self._finish([result])[0]

    def measure_multisine(self, omegas_rad_s) -> list[Measurement]:
        """One multisine record measuring every frequency of ``omegas_rad_s`` (distinct).

        The lines share the record's device time: each measurement's ``rig_s`` is its equal
        share. A single frequency is an ordinary :meth:`measure`. The noise of the record is
        seeded with the index of its first line, and ``n_measured`` advances by the number of
        lines, so a resumed campaign repeats the record exactly.
        """
        lines = [float(w) for w in omegas_rad_s]
        expected = self._expected_gains(lines)  # None: equal amplitudes, one record
        groups = [list(range(len(lines)))] if expected is None else resolvable_groups(expected, self.rig.sensor.dynamic_range)
        if len(groups) > 1:  # one record per group, the measurements in the order asked
            measured = {}
            for group in groups:
                measured.update(zip(group, self.measure_multisine([lines[i] for i in group])))
            return [measured[i] for i in range(len(lines))]
        if len(lines) == 1:
            return [self.measure(lines[0])]
        if self._closed:
            raise DeviceError("sine dwell: measure_multisine() after close()")
        if not isinstance(self.rig.exciter, (MultisineExciter, RecordedMultisineExciter)):
            raise DeviceError(f"multisine record: the exciter of {self.rig.metadata.name!r} plays single sines only "
                              "(use [dwell] signal = \"sine\")")
        for w in lines:
            check_sine_command(self.limits, w, self.settings.amplitude_n)
        plan = plan_multisine(self.settings, self.model, lines)
        longest = record_duration_s(self.settings, plan)
        check_dwell(self.limits, plan.skip_s + plan.window_s)
        signal = design_multisine(lines, self.settings.amplitude_n, longest, weights=None if expected is None else line_weights(expected))

        def start(plan):
            self.safe_exciter.set_multisine(signal, longest)

        estimate = self._estimate

        label = f"multisine record at {', '.join(f'{w:g}' for w in lines)} rad/s"
        return self._finish(self._attempts(label, plan, start, estimate))

    def _expected_gains(self, lines: list[float]) -> np.ndarray | None:
        """``|G|`` of the model's midpoint at ``lines`` when the sensor's resolution is limited
        (a :class:`ResolutionLimitedSensor`): its lines are then split into records it resolves
        and shaped (:func:`~setmem_hil.estimation.multisine.resolvable_groups`,
        :func:`~setmem_hil.estimation.multisine.line_weights`). None otherwise, or while the
        model cannot say (the prior's unbounded residues)."""
        if not isinstance(self.rig.sensor, ResolutionLimitedSensor) or self.model is None or len(lines) == 1:
            return None
        with np.errstate(invalid="ignore", over="ignore"):
            nominal = getattr(self.model, "midpoint", self.model)
            expected = np.abs(nominal.frequency_response(np.array(lines)))
        return expected if np.all(np.isfinite(expected)) and np.all(expected > 0) else None

    def _estimate(self, plan, block, attempt: int, dwell_s: float, extensions: int) -> list[DwellResult] | None:
        """The window's results through :func:`~setmem_hil.estimation.dwell_record.results_from_inputs`
        (what ``reprocess`` runs on the raw record); the inputs of a settled window are kept for it."""
        extra = None
        if self.extra_bound is not None:
            extra = tuple((float(w), float(self.extra_bound(float(w)))) for w in plan.omegas_rad_s)
        inputs = DwellInputs(self.settings, self.model, self.pole_tracker.state(), extra, plan, np.asarray(block.t_s),
                             np.asarray(block.force), np.asarray(block.response), tuple(np.asarray(o) for o in block.others),
                             attempt, dwell_s, extensions)
        results = results_from_inputs(inputs)
        if results is not None:
            self._inputs = inputs
        return results

    def take_raw_records(self) -> list[RawRecord]:
        """The raw records of the dwells since the last call (kind ``sine-dwell``:
        :mod:`setmem_hil.estimation.dwell_record`)."""
        taken, self._raw = self._raw, []
        return taken

    def _finish(self, results: list[DwellResult]) -> list[Measurement]:
        """Count a finished dwell or record, keep its raw record, learn its poles, add its device
        time; each of its points carries an equal share of that time."""
        self.n_measured += len(results)
        self.last_result = results[0]
        sensor = self.rig.sensor
        terms = tuple(sensor.instrument_terms(r.measurement.omega_rad_s) for r in results) if isinstance(sensor, TermsReportingSensor) else None
        inputs = dataclasses.replace(self._inputs, terms=terms)
        self._raw.append(dwell_record(inputs, rig=self.rig.metadata.name))
        if self.settings.learn_poles:
            self._learn(results[0].response_fit)
        self.rig_s += self._device_s
        share = self._device_s / len(results)
        if terms is None and isinstance(sensor, InstrumentTermsSensor):  # terms it cannot state: not re-processable
            return [dataclasses.replace(sensor.corrected(r.measurement, abs(r.force_fit.phasor)), rig_s=share) for r in results]
        return [dataclasses.replace(p, rig_s=share) for p in corrected_points(results, terms)]

    def _attempts(self, label: str, plan, start, estimate):
        """Run a dwell until it gives a result, at most ``max_attempts`` times (see the module docs)."""
        errors: list[str] = []
        last_exc: BaseException | None = None
        self._device_s = 0.0  # rig time of this dwell, every attempt included
        for attempt in range(self.settings.max_attempts):
            try:
                return self._dwell(plan, attempt, start, estimate)
            except DataQualityError as exc:
                safe_stop(self.safe_exciter)
                self._count("discarded_dwell")
                errors.append(f"attempt {attempt + 1}: data discarded: {exc}")
                last_exc = exc
                continue
            except DeviceError as exc:
                safe_stop(self.safe_exciter)
                self._count("device_error")
                errors.append(f"attempt {attempt + 1}: device fault: {exc}")
                last_exc = exc
                self._try_reconnect(errors)
                continue
            except BaseException:
                safe_stop(self.safe_exciter)
                raise
        self._failed_attempts += self.settings.max_attempts
        summary = "; ".join(errors)
        msg = f"{label} failed after {self.settings.max_attempts} attempts ({summary})"
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

    def _dwell(self, plan: DwellPlan | MultisinePlan, attempt: int, start, estimate):
        rig, sensor = self.rig, self.rig.sensor
        if isinstance(rig, MeasurementIndexedRig):
            # attempts of earlier measurements that failed for good get their own streams
            rig.begin_measurement(self.n_measured, self._failed_attempts + attempt)
        if isinstance(sensor, RateConfigurableSensor):
            sensor.set_sample_rate(plan.sample_rate_hz)
        elif abs(rig.metadata.sample_rate_hz - plan.sample_rate_hz) > 1e-9 * plan.sample_rate_hz:
            plan = replan_fixed_rate(plan, rig.metadata.sample_rate_hz)
        # output_guard: zero output however the block ends; a failing stop during an abort is
        # logged and never replaces the original exception (so Ctrl-C stays Ctrl-C)
        with output_guard(self.safe_exciter):
            start(plan)
            timed = isinstance(sensor, InstrumentTermsSensor)  # it knows what its waits and records cost
            settle = sensor.wait if isinstance(sensor, WaitingSensor) else sensor.acquire
            self._timed(settle, plan.skip_s, timed, plan.skip_s + plan.window_s)
            block = self._timed(sensor.acquire, plan.window_s, timed, 0.0)
            rate = sensor.last_sample_rate_hz if timed else plan.sample_rate_hz
            check_block(block, rig.metadata.force_range_n, rig.metadata.response_range, rate)
            dwell_s = plan.skip_s + plan.window_s
            extensions = 0
            while True:
                result = estimate(plan, block, attempt, dwell_s, extensions)
                if result is not None:
                    return result
                if extensions >= self.settings.max_extensions or dwell_s + plan.window_s > self.limits.max_dwell_s:
                    raise DataQualityError(
                        f"response at {', '.join(f'{w:g}' for w in plan.omegas_rad_s)} rad/s not settled after {dwell_s:.1f} s "
                        "(the halves of the window disagree beyond their uncertainty)"
                    )
                # consecutive windows: the next estimate uses the newest window only
                block = self._timed(sensor.acquire, plan.window_s, timed, plan.window_s)
                check_block(block, rig.metadata.force_range_n, rig.metadata.response_range, rate)
                dwell_s += plan.window_s
                extensions += 1

    def _timed(self, take, duration_s: float, timed: bool, untimed_s: float):
        """``take(duration_s)`` with its rig time added to the dwell's, also when it fails (a
        clipped record, a failed levelling): a timed sensor reports what it cost, an untimed
        one costs ``untimed_s``."""
        try:
            return take(duration_s)
        finally:
            self._device_s += self.rig.sensor.last_acquire_s if timed else untimed_s

    # -- lifecycle -------------------------------------------------------------------------
    def close(self) -> None:
        """Zero output and release the rig (idempotent)."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self._atexit)
        try:
            safe_stop(self.safe_exciter)
        finally:
            self.rig.close()

    def __enter__(self) -> "SineDwellExperiment":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


