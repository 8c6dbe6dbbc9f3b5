"""The drive level closed on the measured force, for every sampled rig (issue 26).

A sampled force channel (an oscilloscope's or a DAQ's) measures the force the shaker really
applies; the generator's level is set from it, as the lock-in rig does:

* :class:`LevelledExciter` (the :class:`~setmem_hil.drivers.protocols.Exciter`): a sine, or a
  multisine record uploaded as the generator's arbitrary waveform, comes on at a quarter of the
  target at the nominal ``newton_per_volt`` (later dwells at half, with the gain measured before);
* :class:`ForceLeveller`: short records (``LEVEL_PERIODS`` periods of the lowest frequency)
  re-estimate the drive gain and correct the level, at most ``MAX_STEP_UP`` times per step,
  until the force is within ``LEVEL_TOLERANCE`` of a target that leaves room for the force
  channel's own error (so the true force stays at or below ``max_amplitude_n``); any record whose
  force exceeds ``FORCE_TRIP x max_amplitude_n`` switches the output off and stops the run.
  A correction of at most ``MAX_UNCONFIRMED_STEP`` from a gain measured on the same drive (the
  half level a later dwell starts at) is not measured again: the dwell's own record confirms it
  (:meth:`ForceLeveller.confirm_level`; a force above the tolerance discards the record and
  levels again). A levelling record near the first mode is 12 s; two per record were a sixth
  of a campaign's rig time through the oscilloscope.

A sine's force is its fitted amplitude; an arbitrary waveform's is the scale of the known
points, found by aligning the record with them (:func:`held_waveform_gain`). No I/O of its own:
the rig passes how to take a record.
"""

from __future__ import annotations

import logging
import math
from typing import Callable

import numpy as np

from setmem_hil.drivers.instruments.source import SignalSource, switch_output_off
from setmem_hil.errors import DataQualityError, DeviceRejectedError, MeasuredLimitError, SafetyLimitError
from setmem_hil.estimation.sine_fit import fit_sine

__all__ = ["LevelledExciter", "ForceLeveller", "held_waveform_gain", "level_record_s", "levelling_allowance_s", "FORCE_TRIP",
           "POINTS_PER_PERIOD"]

log = logging.getLogger(__name__)

FORCE_TRIP = 1.05  # x max_amplitude_n: a force above it switches the output off
LEVEL_TOLERANCE = 0.03
LEVEL_PERIODS = 1.5  # periods of the drive in a levelling record
MIN_LEVEL_RECORD_S = 0.02
MAX_LEVEL_STEPS = 6
MAX_STEP_UP = 3.0  # the most one levelling step multiplies the drive by
# a correction up to this factor, from a gain measured on the same drive, is confirmed by the
# dwell's own record instead of a levelling record (a linear amplifier and shaker: the gain
# measured at half the level holds at the level; a nonlinear one shows in that record)
MAX_UNCONFIRMED_STEP = 2.5
# Points per period of a multisine's highest line in the generator's arbitrary waveform. Held
# points add images at m f_arb +- f of relative size about f / (m f_arb); a sampling sensor whose
# rate divides some m f_arb aliases one of them exactly onto its line (the force's phasor, not the
# response's: the structure filters it). Many points, at a rate no sensor rate divides
# (an irrational factor), keep that leak far below the bound.
POINTS_PER_PERIOD = 32 * 1.0618


def _six_digits_down(x: float) -> float:
    """``x`` rounded down to six significant digits."""
    step = 10.0 ** (math.floor(math.log10(x)) - 5)
    return float(f"{math.floor(x / step) * step:.6g}")


def level_record_s(omega_rad_s: float) -> float:
    """A levelling record: ``LEVEL_PERIODS`` periods of the (lowest) drive frequency."""
    return max(LEVEL_PERIODS * 2 * math.pi / omega_rad_s, MIN_LEVEL_RECORD_S)


def levelling_allowance_s(lowest_rad_s: float) -> float:
    """How long an arbitrary waveform plays before its record: the levelling records (each may
    come out 2.5 times longer on a 1-2-5 time base) and the trigger waits."""
    return MAX_LEVEL_STEPS * 2.5 * level_record_s(lowest_rad_s) * 1.2 + 10.0


# how far from where the clock puts it a record is searched for in its waveform: the clock knows
# it to the command latency; a short record of close lines matches other places a second away
ALIGN_WITHIN_S = 0.1


def held_waveform_gain(t_s: np.ndarray, force_n: np.ndarray, points: np.ndarray, rate_hz: float,
                       near_s: float | None = None, within_s: float = ALIGN_WITHIN_S) -> float:
    """Force per unit point of a played arbitrary waveform, from a record of the force that
    starts anywhere in it (or, with ``near_s``, within ``within_s`` of ``near_s`` seconds into
    the waveform): the record on the waveform's sample grid, aligned by circular
    cross-correlation, then the least-squares scale.

    Without ``near_s`` a short record of a long waveform can match a wrong place almost as well
    (a 0.6 s record of lines at 16.6-16.9 rad/s matched 0.3 s away with a gain 20 % small, and the
    drive set from it tripped the force limit). The rigs pass where their clock says the record is."""
    grid = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    r = np.interp(grid, t_s, force_n)
    n = points.size
    if r.size < 8 or r.size > n:
        raise DataQualityError(f"a levelling record of {r.size} points on a waveform of {n}: cannot align them")
    corr = np.fft.irfft(np.conj(np.fft.rfft(r, n)) * np.fft.rfft(points, n), n)
    # normalised by each window's energy: the least-squares fit's quality at every alignment
    # (a running sum: a convolution with a window as long as the record is quadratic in its
    # length, and a 120 s record of a long waveform took minutes)
    running = np.concatenate([[0.0], np.cumsum(np.concatenate([points, points[: r.size - 1]]) ** 2)])
    energy = running[r.size:] - running[: running.size - r.size]
    score = corr * np.abs(corr) / np.maximum(energy, 1e-300)
    if near_s is not None:  # only the shifts within within_s of where the clock puts the record
        centre, half = int(round(near_s * rate_hz)), int(math.ceil(within_s * rate_hz))
        allowed = np.mod(np.arange(centre - half, centre + half + 1), n)
        score = np.full(n, -np.inf)
        score[allowed] = (corr * np.abs(corr) / np.maximum(energy, 1e-300))[allowed]
    shift = int(np.argmax(score))
    # refine within a hold on the record's own samples: the played value at each sample time
    best = (-math.inf, 0.0)
    for offset in np.linspace(-1.0, 1.0, 41):
        k = np.floor((t_s - t_s[0]) * rate_hz + shift + offset).astype(np.int64) % n
        held = points[k]
        gain = float(np.dot(force_n, held) / np.dot(held, held))
        fit = gain * float(np.dot(force_n, held))
        best = max(best, (fit, gain))
    return best[1]


class LevelledExciter:
    """The :class:`~setmem_hil.drivers.protocols.Exciter` of a generator whose level the force
    channel closes (:meth:`ScopeSensor.wait` finishes each :meth:`set_sine`)."""

    FIRST_FRACTION = 0.25  # of the target, with the nominal gain (the first dwell)
    NEXT_FRACTION = 0.5  # with the gain measured at the last frequency

    def __init__(self, source: SignalSource, newton_per_volt: float, max_drive_v: float = math.inf, clock=None):
        self.source, self.max_drive_v, self.clock = source, float(max_drive_v), clock
        self.arbitrary_started = 0.0  # clock time the arbitrary waveform began to play (with a clock)
        self.newton_per_volt = float(newton_per_volt)
        self.gain_estimate = float(newton_per_volt)  # N/V, measured from the force once the output is on
        self.measured = False
        self.on = False
        self.volts = 0.0
        self.omega_rad_s = 0.0
        self.target_n = 0.0
        self.needs_level = False
        self.arbitrary: tuple[np.ndarray, float] | None = None  # the multisine record playing: (points, Sa/s)
        self.confirmed_off = True  # the output read back off (the rig forced it off when it opened)
        self.lowest_rad_s = 0.0
        # what plays, for predicting the response (the scope's ranging): the lines' relative
        # phasors (phases at drive_origin, a clock time) and every level set since the start
        self.lines: tuple[tuple[float, ...], tuple[complex, ...]] = ((), ())
        self.drive_origin = 0.0
        self.drive_steps: list[tuple[float, float]] = []  # (clock time, volts)
        # the waveform's length over what the record and its levelling should need: doubled by the
        # sensor when a record runs past its end (re-records after clipping took the room)
        self.waveform_room = 1.0

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        frequency_hz = omega_rad_s / (2 * math.pi)
        self._check_drive(amplitude_n, frequency_hz)
        if self.arbitrary is not None:  # back to the generator's own sine, the output off meanwhile
            if self.on:
                self.stop()
            self.source.play_sine()
            self.arbitrary = None
        self.omega_rad_s, self.target_n = float(omega_rad_s), float(amplitude_n)
        self.source.set_frequency_hz(frequency_hz)
        self.lines = ((float(omega_rad_s),), (1.0 + 0j,))  # the generator's phase at turn-on is unknown: 0
        self.drive_origin = self._now()
        self._start(amplitude_n)

    # -- multisine records through the generator's arbitrary waveform (issue 26) ---------------
    MIN_POINTS_PER_PERIOD = 8

    def set_multisine_record(self, multisine, duration_s: float) -> None:
        """Upload the record (and room for the levelling) as one arbitrary waveform and play it
        at a quarter (then half) of the target level; the levelling finishes it. Its peak is
        checked against the generator's limits before anything is sent."""
        arb = self.source.profile.arbitrary
        top_hz = max(multisine.omegas_rad_s) / (2 * math.pi)
        # the scope's records may come out longer than asked (1-2-5 time base): room for that too
        length = self.waveform_room * (1.5 * duration_s + levelling_allowance_s(min(multisine.omegas_rad_s)))
        rate = float(f"{POINTS_PER_PERIOD * top_hz:.6g}")  # six digits: a rate every generator reads back as sent
        if length * rate > arb.max_points:
            rate = _six_digits_down(arb.max_points / length)  # within the memory
            if rate < self.MIN_POINTS_PER_PERIOD * top_hz:
                raise DeviceRejectedError("range", f"{self.source.name}: a {length:.0f} s multisine record with lines up to "
                                                   f"{top_hz:.4g} Hz needs {self.MIN_POINTS_PER_PERIOD * top_hz * length:.0f} points; "
                                                   f"the {self.source.model} profile holds {arb.max_points}; nothing was sent")
        force = multisine.force(np.arange(int(math.ceil(length * rate))) / rate)
        peak_n = float(np.max(np.abs(force)))
        # the design holds its peak over the record's duration only; the longer waveform may
        # reach higher: its largest point is levelled to the designed peak, never more
        target_n = min(peak_n, multisine.peak_bound(duration_s))
        self._check_drive(target_n, top_hz)
        if self.on:
            self.stop()
        played = self.source.play_arbitrary(force / peak_n, rate)
        if self.clock is not None:  # it plays from the function's selection on
            self.arbitrary_started = self.clock.now()
        # what the generator plays (its DAC's codes, decoded): the levelling fits the force to it
        self.arbitrary = (np.asarray(played, dtype=float), rate)
        self.omega_rad_s, self.target_n, self.lowest_rad_s = 0.0, target_n, min(multisine.omegas_rad_s)
        # a_k sin(w_k t + phi_k) = Re a_k e^{j (phi_k - pi/2)} e^{j w_k t}, t from the waveform's start
        self.lines = (tuple(multisine.omegas_rad_s),
                      tuple(a / peak_n * complex(np.exp(1j * (phi - np.pi / 2))) for a, phi in zip(multisine.amplitudes_n, multisine.phases_rad)))
        self.drive_origin = self.arbitrary_started
        self._start(target_n)

    def _check_drive(self, amplitude_n: float, frequency_hz: float) -> None:
        lo, hi = self.source.frequency_limits_hz
        nominal_v = amplitude_n / self.newton_per_volt
        if nominal_v > self.max_drive_v or nominal_v > self.source.amplitude_limits_v[1] or not lo <= frequency_hz <= hi:
            raise SafetyLimitError(f"{self.source.name}: {amplitude_n:g} N at {frequency_hz:.6g} Hz needs {nominal_v:.4g} V at the "
                                   f"nominal {self.newton_per_volt:g} N/V (max_drive_v {self.max_drive_v:g} V, instrument "
                                   f"{self.source.amplitude_limits_v[1]:g} V, {lo:g}-{hi:g} Hz); nothing was sent")

    def _now(self) -> float:
        return self.clock.now() if self.clock is not None else 0.0

    def _start(self, amplitude_n: float) -> None:
        fraction = self.NEXT_FRACTION if self.measured else self.FIRST_FRACTION
        self.drive_steps = []
        self.set_volts(fraction * amplitude_n / self.gain_estimate)
        if not self.on:
            self.confirmed_off = False  # from the moment the command may take effect
            self.source.set_output(True)
            self.on = True
        self.needs_level = True

    def set_volts(self, volts: float) -> None:
        vlo, vhi = self.source.amplitude_limits_v
        self.volts = float(min(max(volts, vlo), vhi, self.max_drive_v))
        self.source.set_amplitude_v(self.volts)
        self.drive_steps.append((self._now(), self.volts))

    def stop(self) -> None:
        """Output off, read back; when that fails (the link dropped), once more on a fresh
        connection. Raises :class:`~setmem_hil.errors.OutputNotConfirmedOffError` when neither is
        confirmed (``confirmed_off`` stays False: the output may still be on)."""
        self.on = False
        self.needs_level = False
        self.confirmed_off = False
        switch_output_off(self.source)
        self.confirmed_off = True


class ForceLeveller:
    """Closes the level of a :class:`LevelledExciter` on a sampled force (module docstring).

    ``force_room()`` is the relative room the target leaves for the force channel's error."""

    def __init__(self, exciter: LevelledExciter, max_force_n: float, force_room: Callable[[], float], where: str):
        self.exciter, self.max_force_n, self.force_room, self.where = exciter, float(max_force_n), force_room, where
        self.steps = 0
        self.last_fitted_n = 0.0  # the last record's force as the drive sets it (without the noise's peaks)
        self.unconfirmed = False  # the level was corrected without a record after it (confirm_level)
        self.confirm_always = False  # set once such a level came out high: every level is then measured

    def target_n(self) -> float:
        return self.exciter.target_n / (1.0 + self.force_room())

    def force_peak(self, t_s: np.ndarray, force_n: np.ndarray, position_s: float | None = None) -> float:
        """The force's peak (N) as the drive sets it: a sine's fitted amplitude, or the played
        waveform's scale (its largest point is 1; ``position_s``: where in the waveform the
        record starts, by the clock); above the trip level the output goes off first."""
        if self.exciter.arbitrary is None:
            amplitude = self.last_fitted_n = abs(fit_sine(t_s, force_n, np.array([self.exciter.omega_rad_s]),
                                                          t_ref_s=float(t_s[0])).line(0).phasor)
        else:
            points, rate = self.exciter.arbitrary
            # the clock's room, and the done-polling's (a hundredth of the record at most)
            within = ALIGN_WITHIN_S + 0.01 * float(t_s[-1] - t_s[0])
            self.last_fitted_n = held_waveform_gain(t_s, force_n, points, rate, position_s, within)
            amplitude = max(self.last_fitted_n, float(np.max(np.abs(force_n))))
        if amplitude > FORCE_TRIP * self.max_force_n:
            self.exciter.stop()
            raise MeasuredLimitError(f"{self.where}: measured force {amplitude:.4g} N exceeds max_amplitude_n "
                                   f"{self.max_force_n:g} N by more than 5 %; output switched off")
        return amplitude

    def level(self, take: Callable[[float, float], tuple[np.ndarray, np.ndarray]],
              after: Callable[[float], bool] = lambda ratio: False) -> None:
        """Levelling records until the force is on target. ``take(length_s, min_rate_hz)`` records
        the force; ``after(target / force)`` may re-range the channels and answers True when the
        record must be taken again before its force is trusted."""
        omega = self.exciter.omega_rad_s or self.exciter.lowest_rad_s
        target = self.target_n()
        length = level_record_s(omega)
        rate = 20 * omega / (2 * math.pi) if self.exciter.arbitrary is None else 4 * self.exciter.arbitrary[1]
        for _ in range(MAX_LEVEL_STEPS):
            force_n = self.force_peak(*take(length, rate))  # take: (t_s, force_n[, position_s])
            self.steps += 1
            if after(target / max(force_n, 1e-12)):
                continue
            if force_n <= 0:
                raise DataQualityError(f"{self.where}: no force with {self.exciter.volts:.4g} V of drive: is the amplifier on "
                                       "and the force sensor connected?")
            # never more than MAX_STEP_UP times the drive per step, whatever a measurement says
            self.exciter.gain_estimate = max(force_n / self.exciter.volts, self.exciter.gain_estimate / MAX_STEP_UP)
            self.exciter.measured = True
            self.unconfirmed = False
            if abs(force_n / target - 1.0) <= LEVEL_TOLERANCE:
                break
            step = target / force_n
            self.exciter.set_volts(target / self.exciter.gain_estimate)
            if step <= MAX_UNCONFIRMED_STEP and not self.confirm_always:  # the dwell's record confirms it (confirm_level)
                self.unconfirmed = True
                break
        else:
            log.warning("%s: force level not within %.0f %% of %.3g N after %d steps", self.where, 100 * LEVEL_TOLERANCE,
                        target, MAX_LEVEL_STEPS)
        self.exciter.needs_level = False

    def confirm_level(self) -> None:
        """After a dwell's record (its force through :meth:`force_peak`): a level corrected without
        a levelling record after it (``MAX_UNCONFIRMED_STEP``) must have come out within
        ``LEVEL_TOLERANCE`` above its target; otherwise the record is discarded
        (:class:`~setmem_hil.errors.DataQualityError`: the dwell is taken again) and the next one
        levels with records until the force is confirmed (an amplifier or shaker whose gain
        grows with the level)."""
        if not self.unconfirmed:
            return
        self.unconfirmed = False
        target = self.target_n()
        if self.last_fitted_n > target * (1.0 + LEVEL_TOLERANCE):
            self.confirm_always = True
            raise DataQualityError(f"{self.where}: the force came out at {self.last_fitted_n:.4g} N, "
                                   f"{100 * (self.last_fitted_n / target - 1):.1f} % above its level {target:.4g} N "
                                   "(the drive's gain grows with the level); levelled again with a confirming record")
