"""The stepped-sine measurement over real instruments: a signal source and two lock-ins.

One :meth:`PhasorDwellExperiment.measure` call (a *dwell*) implements the loop's Experiment
protocol (:class:`setmem_hil.model.experiment.Experiment`):

1. **Safety, before anything is sent**, in this order: the procedure's ``[safety]`` limits in
   physical units (rad/s, newtons); then the conversion to instrument units (Hz; peak volts =
   force / ``newton_per_volt``, never above ``max_drive_v``); then the instrument's own limits
   from its profile. A command outside any of them raises
   :class:`~setmem_hil.errors.SafetyLimitError` and nothing is sent.
2. Frequency set and read back on the source; both lock-ins get the same time constant,
   ``tau >= time_constant_cycles / omega`` (the 2-omega ripple is then below 1e-4 of the signal at
   24 dB/oct), and the lock-in's reference frequency is checked against the drive.
3. **Closed-loop level, ramped up**: the drive gain is only nominal, so the output starts at a
   tenth of the nominal voltage and each ramp step re-estimates the gain from the *measured*
   force; the level is then corrected until the measured force is within ``level_tolerance`` of
   the target. The target is ``min(amplitude, max_amplitude_n / (1 + c_f))`` (``c_f``: the force
   sensor's calibration uncertainty), so the actual force at the structure stays within the
   limit; every force reading is checked against ``1.05 max_amplitude_n`` and the output is
   switched off at once if it is exceeded.
   Then both lock-ins are **auto-ranged** (smallest full scale with 3x room; a reading near full
   scale or an overload moves one range up and is read again).
4. **Settling**: readings of both lock-ins spaced by their settling time (independent
   readings); the dwell is settled when the two halves of the last ``2 m`` readings agree
   (:func:`setmem_hil.estimation.phasor_estimate.settling_test`), or ``max_dwell_s`` is reached
   (the halves' difference then widens the bound).
5. The point ``g = (R / s_r) / (F / s_f)``, converted from the response sensor's quantity
   (displacement, velocity or acceleration) to receptance, with the bound of
   :func:`~setmem_hil.estimation.phasor_estimate.phasor_point` plus ``extra_bound(omega)``
   (``|W1(j omega)|`` when ``[identification] unmodelled_bound = "w1"``).
6. **Ramp down and output off**, on every exit path (error, Ctrl-C): the ``finally`` of the
   dwell switches the output off even when the ramp-down fails.

The clock (:class:`setmem_hil.drivers.clock.Clock`) is the wall clock on a real rig and the
emulated bench's virtual clock in simulation: the same code runs both.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from setmem_hil.drivers.clock import Clock
from setmem_hil.drivers.instruments.lockin import LockIn, LockInOverload, ReferenceUnlocked
from setmem_hil.drivers.instruments.source import SignalSource, switch_output_off
from setmem_hil.drivers.safety import check_sine_command
from setmem_hil.errors import DeviceError, DeviceRejectedError, MeasuredLimitError, SafetyLimitError
from setmem_hil.estimation.instrument_terms import to_receptance  # noqa: F401 - also imported from here
from setmem_hil.estimation.phasor_record import OutputSensor, lock_in_record, output_point, reading_ratios, receptance_scale
from setmem_hil.estimation.phasor_estimate import exponential_trend, settling_test
from setmem_hil.estimation.ringdown import FreeResponseBound, leak_time_constant, leak_wait_s, ringdown_wait_s, ringing_modes
from setmem_hil.io.procedure import SafetyLimits
from setmem_hil.model.experiment import Measurement, RawRecord

__all__ = ["SensorChannel", "DriveChannel", "PhasorDwellSettings", "PhasorDwellExperiment", "to_receptance"]

log = logging.getLogger(__name__)

QUANTITIES = ("force", "displacement", "velocity", "acceleration")
FORCE_LIMIT_MARGIN = 1.05  # the measured force may never exceed max_amplitude_n by more than 5 %
# reading spacings in settling times: no common period, so no beat aliases into a constant in all of them
SPACING_PATTERN = (1.0, 1.31, 1.12, 1.47, 1.23)


@dataclass(frozen=True)
class SensorChannel:
    """A sensor wired to a lock-in: its declared sensitivity and what it measures."""

    volt_per_unit: float
    calibration_uncertainty: float = 0.0
    quantity: str = "displacement"


@dataclass(frozen=True)
class DriveChannel:
    """The drive: nominal force per volt (planning only) and the largest voltage ever commanded."""

    newton_per_volt: float
    max_drive_v: float = math.inf


@dataclass(frozen=True)
class PhasorDwellSettings:
    amplitude_n: float = 1.0  # the force level aimed at (capped by the safety limit)
    time_constant_cycles: float = 5.0  # tau >= cycles / omega
    readings_per_half: int = 4
    confidence: float = 0.99
    ramp_fractions: tuple[float, ...] = (0.1, 0.3, 0.6)
    level_tolerance: float = 0.05
    max_level_corrections: int = 4
    reference_tolerance: float = 1e-3


def _point_sensor(sensor: SensorChannel) -> OutputSensor:
    return OutputSensor(sensor.volt_per_unit, sensor.calibration_uncertainty, sensor.quantity)


@dataclass
class PhasorDwellExperiment:
    """The Experiment over a :class:`SignalSource` and force/response :class:`LockIn` s."""

    source: SignalSource
    force: LockIn
    response: LockIn
    force_sensor: SensorChannel
    response_sensor: SensorChannel
    drive: DriveChannel
    limits: SafetyLimits
    clock: Clock
    settings: PhasorDwellSettings = PhasorDwellSettings()
    extra_bound: Callable[[float], float] | None = None
    max_response: float | None = None  # abort limit on the response amplitude (its own units)
    on_measurement: Callable[[int], None] | None = None  # simulation control (noise reseeding)
    owned: tuple = ()  # closed after the instruments (emulators)
    n_measured: int = 0
    counters: dict = field(default_factory=lambda: {"dwells": 0, "level_corrections": 0, "unsettled_dwells": 0, "relocks": 0,
                                                    "reconnects": 0})
    model: object = None  # the current IntervalModel (the prior's box at first): ringing modes to wait out
    _frequency_hz: float = field(default=1.0, init=False, repr=False)  # the drive frequency set last
    _drive_changed_at: float = field(default=0.0, init=False, repr=False)  # clock time of the last level change
    _dwell_start: float = field(default=0.0, init=False, repr=False)
    _free: FreeResponseBound | None = field(default=None, init=False, repr=False)  # the drive history (free-response bound)
    last_ringdown: dict = field(default_factory=dict)  # the last dwell's wait and allowance (benchmarks, log)
    output_confirmed_off: bool = True  # the instruments were opened with the output forced off and read back
    last_dwell_s: float = 0.0
    rig_s: float = 0.0
    gain_estimate: float = 0.0
    closed: bool = False
    identities: dict = field(default_factory=dict)  # instrument name -> identity answer (journaled)
    other_responses: tuple = ()  # more response lock-ins (issue 25): every dwell reads them all
    other_sensors: tuple = ()  # their sensors, in the same order
    output_models: tuple = ()  # every output's interval model, control first (empty: self.model for all)

    @property
    def exciter(self) -> str:
        return getattr(self.source, "where", self.source.name)

    def __post_init__(self) -> None:
        if self.force_sensor.quantity != "force":
            raise SafetyLimitError(f"the force lock-in's sensor measures {self.force_sensor.quantity!r}; it must measure force")
        if len(self.other_responses) != len(self.other_sensors):
            raise ValueError(f"{len(self.other_responses)} other response lock-ins but {len(self.other_sensors)} sensors")
        self.gain_estimate = self.drive.newton_per_volt
        self._raw: list[RawRecord] = []  # raw records not yet taken (take_raw_records)

    @property
    def _responses(self) -> tuple[LockIn, ...]:
        """Every response lock-in, the control output's first."""
        return (self.response, *self.other_responses)

    @property
    def _response_sensors(self) -> tuple[SensorChannel, ...]:
        return (self.response_sensor, *self.other_sensors)

    @property
    def _lockins(self) -> tuple[LockIn, ...]:
        return (self.force, *self._responses)

    def _model_of(self, output: int):
        """Output ``output``'s interval model (its own residues once identified; the shared
        model until then)."""
        return self.output_models[output] if len(self.output_models) > output else self.model

    # -- the Experiment protocol -----------------------------------------------------------------
    def measure(self, omega_rad_s: float) -> Measurement:
        if self.closed:
            raise DeviceError(f"{self.source.name}: measure() after close()")
        target = self._target_force()
        frequency_hz = self._check_command(omega_rad_s, target)
        if self.on_measurement is not None:
            self.on_measurement(self.n_measured)
        start = self._dwell_start = self.clock.now()
        try:
            self.source.set_frequency_hz(frequency_hz)
            tau = self._set_time_constants(omega_rad_s)
            for li in self._lockins:  # every dwell starts on the largest full scale
                li.set_range_for(complex(math.inf, 0.0))
            self._wait_locked(frequency_hz)
            self._level_up(target)
            self._check_reference(frequency_hz)
            self._wait_out_ringing(omega_rad_s, tau)
            self._auto_range()  # after the wait: a lightly damped response is still growing before it
            all_f, all_r, times = self._settle_and_read(omega_rad_s, target)
            window = slice(-2 * self.settings.readings_per_half, None)
            force_v = all_f[window]
            allowances = [self._free_response_allowance(omega_rad_s, tau, times[window], force_v, k) for k in range(len(all_r))]
            self._ramp_down(target)
        except BaseException:
            self._output_off_keeping_the_cause()  # Ctrl-C stays Ctrl-C, a fault stays that fault
            raise
        else:
            self._output_off()
        finally:
            self.last_dwell_s = self.clock.now() - start
            self.rig_s += self.last_dwell_s
        self.counters["dwells"] += 1
        self.n_measured += 1
        window_n = 2 * self.settings.readings_per_half
        extra = float(self.extra_bound(omega_rad_s)) if self.extra_bound is not None else 0.0
        force, sensors = _point_sensor(self.force_sensor), [_point_sensor(s) for s in self._response_sensors]
        record = lock_in_record(omega_rad_s, all_f, all_r, times, window_n, force, sensors, self.settings.confidence, allowances,
                                extra, {"time_constant_s": float(tau), "lock_ins": [li.name for li in self._lockins]})
        self._raw.append(record)
        outputs = [output_point(omega_rad_s, all_f, r, times, window_n, force, sensors[k], self.settings.confidence, allowances[k], extra)
                   for k, r in enumerate(all_r)]
        self.last_ringdown["allowance"], self.last_ringdown["trend"] = allowances[0], outputs[0].trend
        (g, bound, point), others = (outputs[0].response, outputs[0].bound, outputs[0].point), tuple((o.response, o.bound) for o in outputs[1:])
        if self._free is not None:  # what the structure did: caps its free ringing from now on
            own = point.bound * receptance_scale(omega_rad_s, self.response_sensor.quantity)  # statistical: no allowance fed back
            self._free.record_motion(self.clock.now(), (abs(g) + own) * point.force_amplitude)
        log.info("dwell at %.6g rad/s: %d readings, %.1f s, force %.4g N, |g| %.4g, bound %.3g%s", omega_rad_s, point.n_readings,
                 self.last_dwell_s, point.force_amplitude, abs(g), bound, f", {len(others)} more outputs" if others else "")
        return Measurement(float(omega_rad_s), complex(g), float(bound), rig_s=float(self.last_dwell_s), others=others)

    def _expected_response(self, omega_rad_s: float) -> float:
        """|G| of the model's midpoint (nan while residues are unbounded)."""
        with np.errstate(invalid="ignore"):
            return abs(complex(np.ravel(self.model.midpoint.frequency_response(np.array([omega_rad_s])))[0]))

    def update_model(self, model) -> None:
        """The campaign's interval model after each identification: tighter damping bounds
        shorten the wait and the allowance of later dwells."""
        self.model = model

    def update_output_models(self, models) -> None:
        """Every output's interval model (control first; several sensors, issue 25): each
        output's free-response allowance uses its own residues."""
        self.output_models = tuple(models)

    def _wait_out_ringing(self, omega_rad_s: float, tau: float) -> None:
        """Wait ``DECAY_TIMES`` decay times of every mode whose beat passes the output filter
        (counted from the last level change; capped so that the readings still fit in
        ``max_dwell_s``), and for filtered leaks (:func:`leak_wait_s`)."""
        if self.model is None:
            return
        order = self._filter_order
        modes = ringing_modes(self.model, omega_rad_s, tau, order)
        elapsed = self.clock.now() - self._drive_changed_at
        wanted = ringdown_wait_s(modes)
        leak = 0.0
        if self._free is not None:
            leak = leak_wait_s(self._free, self.model, omega_rad_s, tau, order, self.clock.now(), self._target_force(),
                               self._expected_response(omega_rad_s))
        readings_s = 2 * self.settings.readings_per_half * self._settle_time() * max(SPACING_PATTERN)
        room = self.limits.max_dwell_s - (self.clock.now() - self._dwell_start) - readings_s
        wait = max(0.0, min(max(wanted - elapsed, leak), room))
        self.last_ringdown = {"omega_rad_s": omega_rad_s, "wanted_s": wanted, "leak_wait_s": leak, "waited_s": wait,
                              "decay_times_s": [m.decay_time_s for m in modes if m.passes]}
        if wait > 0:
            self._wait(wait)

    def _free_response_allowance(self, omega_rad_s: float, tau: float, times: np.ndarray, force_v: np.ndarray, output: int = 0) -> float:
        """What the modes' free response may still add to the mean of output ``output``'s
        readings (receptance units; :class:`~setmem_hil.estimation.ringdown.FreeResponseBound`
        with that output's residues)."""
        if self._free is None:
            return 0.0
        force_n = self._force_amplitude(complex(np.mean(force_v)))
        return self._free.allowance(self._model_of(output), times, omega_rad_s, tau, self._filter_order, force_n)

    def _still_ringing(self, forces: list, responses: list, times: list, window: np.ndarray, output: int = 0) -> bool:
        """A ringing mode the halves test cannot see (its beat inflates the scatter instead of
        shifting the mean): the exponential fit of every reading still shows a transient above
        the fit's residual noise. Reading on lets it decay (up to ``max_dwell_s``)."""
        _, ringing_now = exponential_trend(np.array(times), self._ratios(forces, responses, output), complex(window.mean()),
                                           self.settings.confidence)
        return ringing_now > 0

    def _ratios(self, forces, responses, output: int = 0) -> np.ndarray:
        """Each reading's response per force, in the sensors' units."""
        return reading_ratios(forces, responses, _point_sensor(self.force_sensor), _point_sensor(self._response_sensors[output]))

    def take_raw_records(self) -> list[RawRecord]:
        """The raw records of the dwells since the last call (kind ``lock-in-readings``:
        :mod:`setmem_hil.estimation.phasor_record`)."""
        taken, self._raw = self._raw, []
        return taken

    @property
    def _filter_order(self) -> int:
        return max(li.profile.filter_order for li in self._lockins)

    def confirm_output_off(self) -> None:
        """Output off, read back (a fresh connection if the link failed); raises when it cannot
        be confirmed (:class:`~setmem_hil.errors.OutputNotConfirmedOffError`)."""
        self._output_off()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._output_off()
        finally:
            for inst in (self.source, *self._lockins, *self.owned):
                try:
                    inst.close()
                except Exception as exc:  # noqa: BLE001 - close everything, report nothing over the cause
                    log.error("closing %s: %r", getattr(inst, "name", inst), exc)

    def __enter__(self) -> "PhasorDwellExperiment":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- steps ------------------------------------------------------------------------------------
    def _target_force(self) -> float:
        cap = self.limits.max_amplitude_n / (1.0 + self.force_sensor.calibration_uncertainty)
        return min(self.settings.amplitude_n, cap)

    def _check_command(self, omega_rad_s: float, force_n: float) -> float:
        """Physical limits, then instrument units, then the instrument's limits; returns Hz."""
        check_sine_command(self.limits, omega_rad_s, force_n, self.source.name)
        frequency_hz = omega_rad_s / (2 * math.pi)
        volts = force_n / self.drive.newton_per_volt
        if volts > self.drive.max_drive_v:
            raise SafetyLimitError(f"{self.source.name}: {force_n:g} N needs {volts:.4g} V at the nominal {self.drive.newton_per_volt:g} N/V, "
                                   f"above max_drive_v = {self.drive.max_drive_v:g} V; nothing was sent")
        lo, hi = self.source.frequency_limits_hz
        if not lo <= frequency_hz <= hi:
            raise SafetyLimitError(f"{self.source.name}: {frequency_hz:.6g} Hz outside the {self.source.model}'s range [{lo:g}, {hi:g}] Hz; nothing was sent")
        vlo, vhi = self.source.amplitude_limits_v
        if volts > vhi:
            raise SafetyLimitError(f"{self.source.name}: {volts:.4g} V peak above the {self.source.model}'s {vhi:g} V; nothing was sent")
        return frequency_hz

    def _set_time_constants(self, omega_rad_s: float) -> float:
        """``time_constant_cycles / omega``, or longer where a mode still rings hard enough from
        an earlier dwell that its beat would leak through (:func:`leak_time_constant`)."""
        wanted = self.settings.time_constant_cycles / omega_rad_s
        if self._free is not None:
            values = self.response.profile.time_constants_s
            base = next((v for v in values if v >= wanted), values[-1])
            wanted = leak_time_constant(self._free, self.model, omega_rad_s, self._filter_order, self.clock.now(), values, base,
                                        self._target_force(), self._expected_response(omega_rad_s))
        tau = self.force.set_time_constant(wanted)
        taus = [li.set_time_constant(tau) for li in self._responses]
        if any(t != tau for t in taus):  # different instruments: the longest for all
            tau = max(taus + [tau])
            for li in self._lockins:
                li.set_time_constant(tau)
        return tau

    def _wait(self, duration_s: float) -> None:
        """Let time pass, refreshing the source's dead-man often enough (a Modbus watchdog)."""
        step = getattr(self.source, "keepalive_interval_s", math.inf)
        end = self.clock.now() + duration_s
        while (left := end - self.clock.now()) > 0:
            self.clock.sleep(min(left, step))
            self.source.keepalive()

    def _settle_time(self) -> float:
        return max(li.settling_time_s for li in self._lockins)

    def _drive_volts(self, volts: float) -> float:
        vlo, vhi = self.source.amplitude_limits_v
        return float(min(max(volts, vlo), vhi, self.drive.max_drive_v))

    def _read_force(self) -> complex:
        """One force reading, checked against the force abort limit (output off if exceeded)."""
        f_v = self._read(self.force)
        self.source.keepalive()
        actual = math.sqrt(2.0) * abs(f_v) / self.force_sensor.volt_per_unit * (1.0 + self.force_sensor.calibration_uncertainty)
        if actual > FORCE_LIMIT_MARGIN * self.limits.max_amplitude_n:
            self._output_off()
            raise MeasuredLimitError(f"{self.force.name}: measured force {actual:.4g} N (with its calibration uncertainty) exceeds "
                                   f"max_amplitude_n {self.limits.max_amplitude_n:g} N by more than 5 %; output switched off")
        return f_v

    def _force_amplitude(self, f_v: complex) -> float:
        return math.sqrt(2.0) * abs(f_v) / self.force_sensor.volt_per_unit

    def _level_up(self, target: float) -> None:
        """Output on at a tenth of the nominal level, ramp up re-estimating the gain from the
        measured force, then correct the level until the force is on target."""
        volts = self._drive_volts(self.settings.ramp_fractions[0] * target / self.gain_estimate)
        self.source.set_amplitude_v(volts)
        self.output_confirmed_off = False  # from the moment the command may have taken effect
        self.source.set_output(True)
        self._drive_changed(volts)
        for fraction in (*self.settings.ramp_fractions[1:], 1.0):
            self._wait(self._settle_time())
            self._update_gain(volts)
            volts = self._set_drive(fraction * target / self.gain_estimate)
        for _ in range(self.settings.max_level_corrections):
            self._wait(self._settle_time())
            force = self._update_gain(volts)
            if abs(force / target - 1.0) <= self.settings.level_tolerance:
                return
            volts = self._set_drive(target / self.gain_estimate)
            self.counters["level_corrections"] += 1
        log.warning("%s: force level not within %.0f %% of %.3g N after %d corrections", self.source.name,
                    100 * self.settings.level_tolerance, target, self.settings.max_level_corrections)

    # the force a drive voltage may produce, for the free-response bound: the gain estimate with
    # room for its error (the first steps use the nominal gain), never above the force abort limit
    GAIN_ROOM = 1.25

    def _set_drive(self, volts: float) -> float:
        volts = self._drive_volts(volts)
        self.source.set_amplitude_v(volts)
        self._drive_changed(volts)
        return volts

    def _drive_changed(self, volts: float) -> None:
        """Record a change of the drive (for the wait and the free-response bound)."""
        self._drive_changed_at = self.clock.now()
        if self.model is None:
            return
        force_max = FORCE_LIMIT_MARGIN * self.limits.max_amplitude_n
        if self._free is None:
            self._free = FreeResponseBound(force_max)
        force = min(force_max, volts * self.gain_estimate * self.GAIN_ROOM * (1.0 + self.force_sensor.calibration_uncertainty))
        self._free.drive(self._drive_changed_at, 2 * math.pi * self._frequency_hz, force)

    def _update_gain(self, volts: float) -> float:
        force = self._force_amplitude(self._read_force())
        if force <= 0 or volts <= 0:
            raise DeviceRejectedError("instrument", f"{self.force.name}: no force measured with {volts:.4g} V of drive: is the amplifier on and the force sensor connected?")
        self.gain_estimate = force / volts
        return force

    MAX_RANGE_STEPS = 6

    def _auto_range(self) -> None:
        """Both lock-ins to the smallest full scale with room for the signal (better resolution
        and dynamic reserve for small responses); the readings keep their units (volts)."""
        changed = False
        for li in self._lockins:
            changed |= li.set_range_for(self._read(li))
        if changed:
            self._wait(self._settle_time() / 10.0)

    def _read(self, li: LockIn) -> complex:
        """One reading; on an overload or a reading near full scale the range goes up and the
        reading is taken again (an overload at the largest range stops the dwell)."""
        for _ in range(self.MAX_RANGE_STEPS):
            try:
                z = li.read_xy()
            except ReferenceUnlocked:  # a momentary unlock: wait for the lock, then for the filter
                self.counters["relocks"] += 1
                self._wait_locked(self._frequency_hz, after_unlock=True)
                continue
            except LockInOverload as exc:
                if not li.range_up():
                    raise DeviceRejectedError("overload", f"{exc} at the largest full scale: lower volt_per_unit or the force level") from None
                self._wait(self._settle_time() / 10.0)
                continue
            if li.near_full_scale(z) and li.range_up():
                self._wait(self._settle_time() / 10.0)
                continue
            return z
        try:
            return li.read_xy()
        except LockInOverload as exc:
            raise DeviceRejectedError("overload", f"{exc} after {self.MAX_RANGE_STEPS} range changes") from None

    # the reference relocks after every frequency (and time constant) change: wait at most
    # RELOCK_MIN_S, or RELOCK_PERIODS reference periods plus RELOCK_TAUS time constants if longer
    # (a PLL needs a number of cycles to lock; the output filter then needs its settling time).
    # A judgement, not a datasheet figure: the SR830 and SR860 lock within a few cycles above 10 Hz.
    RELOCK_MIN_S = 1.0
    RELOCK_PERIODS = 50.0
    RELOCK_TAUS = 10.0

    def relock_timeout_s(self, frequency_hz: float) -> float:
        tau = max(li.time_constant_s for li in self._lockins)
        return max(self.RELOCK_MIN_S, self.RELOCK_PERIODS / frequency_hz + self.RELOCK_TAUS * tau)

    def _wait_locked(self, frequency_hz: float, after_unlock: bool = False) -> None:
        """Poll both lock-ins until their reference is locked; a lock regained after an unlock
        also waits the filters' settling time (the output holds the unlocked stretch)."""
        self._frequency_hz = frequency_hz
        timeout = self.relock_timeout_s(frequency_hz)
        poll = max(0.005, timeout / 200.0)
        start = self.clock.now()
        waited = False
        for li in self._lockins:
            while not li.locked():
                waited = True
                if self.clock.now() - start > timeout:
                    raise DeviceRejectedError("unlocked", f"{li.where}: reference not locked {timeout:.3g} s after setting "
                                              f"{frequency_hz:.6g} Hz: is the generator's sync output wired to the reference input?")
                self._wait(poll)
        if waited or after_unlock:
            self._wait(self._settle_time())

    def _check_reference(self, frequency_hz: float) -> None:
        for li in self._lockins:
            ref = li.reference_frequency_hz()
            if abs(ref / frequency_hz - 1.0) > self.settings.reference_tolerance:
                raise DeviceRejectedError("instrument", f"{li.where}: reference at {ref:.6g} Hz, the drive at {frequency_hz:.6g} Hz: "
                                          "is the generator's sync output wired to the reference input?")

    def _settle_and_read(self, omega_rad_s: float, target: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Readings spaced irregularly (``SPACING_PATTERN`` times the filters' settling time, so
        that a ringing mode's beat cannot alias into a constant) until the settling test passes
        twice in a row for every output; returns every force reading, every output's response
        readings (one row per output, control first) and their clock times (the window is the
        last ``2 m``)."""
        m = self.settings.readings_per_half
        start = self.clock.now()
        forces: list[complex] = []
        responses: list[list[complex]] = [[] for _ in self._responses]
        times: list[float] = []
        passes = 0
        while True:
            times.append(self.clock.now())
            forces.append(self._read_force())
            for readings, li in zip(responses, self._responses):
                readings.append(self._read(li))
            self._check_response(responses[0][-1], omega_rad_s)
            spacing = self._settle_time() * SPACING_PATTERN[len(forces) % len(SPACING_PATTERN)]
            if len(forces) >= 2 * m:
                settled = all(self._output_settled(forces, r, times, k) for k, r in enumerate(responses))
                passes = passes + 1 if settled else 0
                if passes >= 2:  # two windows in a row: one lucky draw does not end the dwell
                    return np.array(forces), np.array(responses), np.array(times)
                if self.clock.now() - start + spacing > self.limits.max_dwell_s:
                    self.counters["unsettled_dwells"] += 1
                    log.warning("dwell at %.6g rad/s not settled within max_dwell_s = %g s; the bound includes the drift",
                                omega_rad_s, self.limits.max_dwell_s)
                    return np.array(forces), np.array(responses), np.array(times)
            self._wait(spacing)

    def _output_settled(self, forces: list, responses: list, times: list, output: int) -> bool:
        """The halves test and the exponential-trend test on one output's last ``2 m`` readings."""
        m = self.settings.readings_per_half
        ratio = self._ratios(forces[-2 * m:], responses[-2 * m:], output)
        return settling_test(ratio, self.settings.confidence) and not self._still_ringing(forces, responses, times, ratio, output)

    def _check_response(self, r_v: complex, omega_rad_s: float) -> None:
        if self.max_response is None:
            return
        amplitude = math.sqrt(2.0) * abs(r_v) / self.response_sensor.volt_per_unit
        if amplitude > self.max_response:
            self._output_off()
            raise MeasuredLimitError(f"{self.response.name}: response amplitude {amplitude:.4g} at {omega_rad_s:.6g} rad/s exceeds "
                                   f"[safety] max_response {self.max_response:g}; output switched off")

    def _ramp_down(self, target: float) -> None:
        volts = target / self.gain_estimate
        for fraction in reversed(self.settings.ramp_fractions):
            self._set_drive(fraction * volts)
            self._wait(self._settle_time() / 10.0)

    def _output_off_keeping_the_cause(self) -> None:
        """Output off while an exception is on its way out: a failure is logged, never raised."""
        try:
            self._output_off()
        except BaseException as exc:  # noqa: BLE001 - the original exception must propagate
            log.error("%s", exc)

    def _output_off(self) -> None:
        """Switch the output off and read it back; when that fails (the link dropped), open a
        fresh connection and try once more. Raises :class:`OutputNotConfirmedOffError` when
        neither is confirmed: the output may still be on."""

        def counted() -> None:
            self.counters["reconnects"] += 1

        self.output_confirmed_off = False
        if not switch_output_off(self.source, self.exciter, counted):
            self._drive_changed(0.0)
        self.output_confirmed_off = True


